//! Minimum-curvature racing line (Heilmeier et al. 2020) and its speed profile.
//!
//! # Conventions
//! Curves run in the direction of travel; the unit normal `n_i = (-t_y, t_x)` points to the
//! **left** of the unit tangent `t_i` (as [`crate::Projection::lateral`] does), curvature is
//! positive for left turns, and the raceline is `r_i = p_i + α_i n_i`, so `α_i > 0` moves node `i`
//! towards the left wall. (The TUMFTM code and REFERENCE.md §6 use a right-pointing normal, hence
//! their swapped bounds.) The car's centre must keep `w_car/2 + margin` from the walls:
//! `-(w_right - w_car/2 - margin) ≤ e ≤ w_left - w_car/2 - margin` for its lateral offset `e` from
//! the centreline polyline, measured as [`ClosedCurve::project`] does.
//!
//! # Nodes and gates
//! The nodes `p_0 … p_{n-1}` lie about `step` apart at arc lengths `s_i`; node `i` is the mean of
//! the centreline sampled over `s_i ± w_i` (`w_i = step` unless widened, below), which removes
//! the pixel staircase of map-derived centrelines (one pixel = 5 cm) but moves the nodes off the
//! centreline by up to a few centimetres, so the corridor is always measured against the original
//! polyline. The normals `n_i` come from the spline below through the nodes, the reference, and
//! stay fixed, so every iteration measures `α` from the same nodes. Each spline segment carries
//! `k = ⌈step / 0.1 m⌉` gates at equal parameter steps (the first at its node): a point `g` with
//! unit normal `n_g` and the offsets `[lo_g, hi_g]` along `n_g` at which `e` reaches its limits
//! (three fixed-point steps `a ← a + limit - e(g + a n_g)` from `a = 0`).
//!
//! The offsets must stay short of the reference's centres of curvature: where the reference has
//! curvature `κ`, the curve at constant offset `α` runs at `1 - α κ` times its speed, so at
//! `α κ = 1` the normals of neighbouring gates cross, and beyond it the curve runs backwards.
//! Averaging over `±step` spreads a corner of the centreline through an angle `θ` over only about
//! `2 step`, a mean radius of `2 step / θ` (about 0.5 m in the sharp hairpin of f1_aut, 0.26 m at
//! its tightest), which can be less than the corridor's inner width; the QP, which holds the chord
//! lengths fixed, then moves neighbouring nodes onto the crossing, and the spline through the
//! nearly coincident nodes has a cusp. So the gates are kept to `α κ ≤ 0.8`, with `κ` the
//! reference's curvature at the gate: per unit length of the reference, the line's derivative
//! `(1 - α κ) t + α' n` then keeps a length of at least 0.2. Where a gate of segment `i` reaches
//! beyond `α = 0.8 / κ`, the windows of the nodes `i-1 … i+2` that shape the segment become
//! `w_j ← max(w_j, 1.5 w_i)`, every window is raised to `w_j ≥ w_m - |s_j - s_m| / 4` for all `m`
//! so that neighbouring nodes average alike, and the reference and its gates are rebuilt, which
//! spreads the corner over more nodes. Of the first reference and at most six widened ones, the
//! one whose gates reach least far beyond `0.8 / κ` in sum is kept, and what still reaches beyond
//! is cut off.
//!
//! The raceline's vertices are the spline at the same parameters, and the QP keeps each one's
//! offset along its gate's normal within the gate. Where a vertex still pokes out (the points
//! slide a little along a kinked polyline), its gate is tightened from the vertex's current offset
//! by the excess plus 0.1 mm and the last QP re-solved, at most three times.
//!
//! # Spline
//! Through any node set `x_i` (each coordinate alike) runs the closed C² cubic spline parametrised
//! by chord length: on segment `i`, of length `h_i = |x_{i+1} - x_i|`, with `u ∈ [0, h_i]` and
//! node second derivatives `M_i`,
//!
//! ```text
//! x(u)  = x_i + u (D_i - h_i (2 M_i + M_{i+1}) / 6) + M_i u²/2 + (M_{i+1} - M_i) u³ / (6 h_i),
//! D_i   = (x_{i+1} - x_i) / h_i,
//! h_{i-1} M_{i-1} + 2 (h_{i-1} + h_i) M_i + h_i M_{i+1} = 6 (D_i - D_{i-1})   (indices mod n),
//! ```
//!
//! i.e. `T M = R x` with `T` symmetric positive definite cyclic tridiagonal (continuity of value,
//! first and second derivative, with the segment-length scaling built into `h`). The node
//! derivatives are `x'_i = D_i - h_i (2 M_i + M_{i+1}) / 6` and `x''_i = M_i`.
//!
//! # Quadratic programme
//! The curvature at node `i` is `κ_i = (x'_i y''_i - y'_i x''_i) / (x'_i² + y'_i²)^{3/2}`. Holding
//! the first derivatives and the segment lengths `h` at those of the current line, the second
//! derivatives are linear in `α`: `M_x = T⁻¹ R (p_x + diag(n_x) α)`, likewise for `y`, so
//! `κ ≈ K₀ + E α` with `E = diag(x'/|v|³) S diag(n_y) - diag(y'/|v|³) S diag(n_x)`, `S = T⁻¹ R`.
//! Rather than forming the dense `E`, the QP keeps `M_x, M_y` as variables tied to `α` by the
//! sparse equalities `T M_x - R diag(n_x) α = R p_x` (and for `y`), which keeps the KKT system
//! sparse even with the curvature limit `|κ_i| ≤ κ_max`:
//!
//! ```text
//! minimise   ½ Σ_i κ_i²,   κ_i = (x'_i M_{y,i} - y'_i M_{x,i}) / |v_i|³
//! subject to the spline equalities, |κ_i| ≤ κ_max and, for each gate g at τ ∈ [0, 1) on
//!            segment i, lo_g ≤ n_g · (x(τ h_i) - g) ≤ hi_g, where the spline point
//!            x(τ h_i) = r_i (1 - τ) + r_{i+1} τ + h_i² (c_i(τ) M_i + c_{i+1}(τ) M_{i+1}),
//!            r_i = p_i + α_i n_i,  c_i(τ) = -τ/3 + τ²/2 - τ³/6,  c_{i+1}(τ) = (τ³ - τ)/6.
//! ```
//!
//! This is Heilmeier's linearisation. Its error grows with the offset: shifting a corner of
//! curvature `κ` by a constant `α` towards its inside gives `κ / (1 - ακ)`, while the linearisation
//! predicts `κ (1 - ακ)`, so the optimum leans to the inside of long constant-radius corners (a
//! circular track converges to its innermost circle). That is the shorter and, at the lateral
//! limit, quicker line (`T = 2π √(R / a_lat)` round a circle); fully linearising `κ` in the first
//! derivatives too instead gave longer, slower lines on f1_esp.
//!
//! It is solved by Clarabel. When the curvature limit makes the linearised problem infeasible it
//! is dropped for that QP. The spline is then rebuilt through the new line by its own chord
//! lengths and the QP re-linearised, until no node moves more than 1 mm or `max_iterations` QPs
//! have run. The result is the last QP's own spline (on its linearisation's knots), whose vertices
//! are exactly the gated points.
//!
//! # Speed profile
//! Each vertex, about 0.1 m apart, gets the limit
//! `v_i ≤ min(v_max, √(a_lat / |κ_i|))`; a forward pass accelerates with what the friction ellipse
//! leaves, `a_x ≤ a_long √(max(0, 1 - (v² |κ| / a_lat)²))`, and a backward pass brakes likewise.
//! Both passes run twice around the lap starting at its slowest limit, so the profile is consistent
//! across the seam. The longitudinal acceleration is `a_i = (v_{i+1}² - v_i²) / (2 Δs_i)`.

use crate::error::{Result, TrackError};
use crate::path::{Centreline, ClosedCurve, Raceline};
use clarabel::algebra::CscMatrix;
use clarabel::solver::{
    DefaultSettings, DefaultSolver, IPSolver, SolverError, SolverStatus,
    SupportedConeT::{NonnegativeConeT, ZeroConeT},
};
use nalgebra::{DMatrix, DVector, Point2, Vector2};
use serde::{Deserialize, Serialize};

/// Spacing of the vertices of the returned raceline (m).
const OUTPUT_STEP: f64 = 0.1;
/// The iteration stops once no node moves more than this (m).
const TOLERANCE: f64 = 1e-3;
/// Rounds of tightening the gates where the line still leaves the corridor.
const REPAIRS: usize = 3;
/// Extra tightening per repair (m).
const REPAIR_EXTRA: f64 = 1e-4;
/// The nodes average the centreline over `±window` sampled at `step / SMOOTHING`.
const SMOOTHING: f64 = 8.0;
/// Largest `α κ` a gate allows towards the inside of a bend of the reference (see the module doc).
const FOLD: f64 = 0.8;
/// Rounds of widening the averaging windows where a gate reaches beyond [`FOLD`].
const WIDENINGS: usize = 6;
/// Factor by which a round widens a window.
const WIDEN: f64 = 1.5;
/// Largest change of the window per unit arc length between neighbouring nodes.
const TAPER: f64 = 0.25;

/// Vehicle limits and optimiser settings for the min-curvature raceline.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RacelineParams {
    /// Top speed (m/s).
    pub v_max: f64,
    /// Lateral acceleration limit, a bound on `v² |κ|` (m/s²). The default, 5, is half the tyre
    /// limit `μ g ≈ 10`: at 10 a pure-pursuit car cannot hold the line at full speed, and the
    /// paper's shipped racelines stay below 3.8.
    pub a_lat: f64,
    /// Longitudinal acceleration and braking limit (m/s²).
    pub a_long: f64,
    /// Car width (m); the car's centre keeps half of it from the walls.
    pub car_width: f64,
    /// Extra clearance to the walls (m). 0.25 m keeps pure-pursuit rivals (which cut corners and
    /// run wide on exits by up to ~0.2 m) off the walls in every evaluation context on f1_esp and
    /// f1_gbr at the paper runs' speed factor 0.8; 0.2 m does not (`c = (0.3, 0.3)` on f1_esp),
    /// and 0.3 m bends the line on narrow maps up to 1.6 × as much as their shipped one (Monza).
    pub margin: f64,
    /// Spacing of the optimisation nodes along the centreline (m).
    pub step: f64,
    /// Curvature limit (1/m), dropped when infeasible; `.inf` disables it.
    pub kappa_max: f64,
    /// Maximum number of re-linearisations.
    pub max_iterations: usize,
}

impl Default for RacelineParams {
    fn default() -> Self {
        Self {
            v_max: 8.0,
            a_lat: 5.0,
            a_long: 6.0,
            car_width: 0.31,
            margin: 0.25,
            step: 0.5,
            kappa_max: 1.0,
            max_iterations: 5,
        }
    }
}

impl RacelineParams {
    /// Checks every field's range.
    pub fn validate(&self) -> Result<()> {
        let invalid = |field: &str, message: String| {
            Err(TrackError::Invalid {
                what: format!("raceline.{field}"),
                message,
            })
        };
        for (field, v) in [
            ("v_max", self.v_max),
            ("a_lat", self.a_lat),
            ("a_long", self.a_long),
            ("step", self.step),
        ] {
            if !(v > 0.0 && v.is_finite()) {
                return invalid(field, format!("must be finite and > 0, got {v}"));
            }
        }
        for (field, v) in [("car_width", self.car_width), ("margin", self.margin)] {
            if !(v >= 0.0 && v.is_finite()) {
                return invalid(field, format!("must be finite and >= 0, got {v}"));
            }
        }
        if self.kappa_max.is_nan() || self.kappa_max <= 0.0 {
            return invalid(
                "kappa_max",
                format!("must be > 0 (.inf for none), got {}", self.kappa_max),
            );
        }
        if self.max_iterations == 0 {
            return invalid("max_iterations", "must be >= 1, got 0".into());
        }
        Ok(())
    }
}

/// Closed C² cubic spline through a node set on knots `h` (see the module doc).
struct Spline {
    pts: Vec<Point2<f64>>,
    /// Parameter length of each segment (its chord length when built by [`Spline::new`]).
    h: Vec<f64>,
    /// Second derivative at each node.
    m: Vec<Vector2<f64>>,
}

impl Spline {
    /// The spline through `pts` parametrised by chord length.
    fn new(pts: Vec<Point2<f64>>) -> Result<Self> {
        let n = pts.len();
        let h: Vec<f64> = (0..n).map(|i| (pts[(i + 1) % n] - pts[i]).norm()).collect();
        if let Some(i) = h.iter().position(|&h| h < 1e-6) {
            return Err(TrackError::Optimisation(format!(
                "raceline nodes {i} and {} coincide at ({:.3}, {:.3}): the track is wider there \
                 than its corner radius; check the centreline widths",
                (i + 1) % n,
                pts[i].x,
                pts[i].y
            )));
        }
        let mut t = DMatrix::zeros(n, n);
        let (mut rx, mut ry) = (DVector::zeros(n), DVector::zeros(n));
        for i in 0..n {
            let prev = (i + n - 1) % n;
            t[(i, i)] = 2.0 * (h[prev] + h[i]);
            t[(i, (i + 1) % n)] = h[i];
            t[((i + 1) % n, i)] = h[i];
            for (j, c) in rhs_stencil(&h, i) {
                rx[i] += c * pts[j].x;
                ry[i] += c * pts[j].y;
            }
        }
        let chol = t.cholesky().ok_or_else(|| {
            TrackError::Optimisation("the spline system is not positive definite".into())
        })?;
        let (mx, my) = (chol.solve(&rx), chol.solve(&ry));
        let m = (0..n).map(|i| Vector2::new(mx[i], my[i])).collect();
        Ok(Self { pts, h, m })
    }

    fn len(&self) -> usize {
        self.pts.len()
    }

    /// [`Spline::eval`] at the `k`-th parameter step from node 0, `per_segment` steps a segment.
    fn sample(&self, k: usize, per_segment: usize) -> (Point2<f64>, Vector2<f64>, Vector2<f64>) {
        let i = k / per_segment;
        self.eval(i, self.h[i] * (k % per_segment) as f64 / per_segment as f64)
    }

    /// Point, first and second derivative at `u ∈ [0, h_i]` along segment `i`.
    fn eval(&self, i: usize, u: f64) -> (Point2<f64>, Vector2<f64>, Vector2<f64>) {
        let j = (i + 1) % self.len();
        let (h, mi, mj) = (self.h[i], self.m[i], self.m[j]);
        let slope = (self.pts[j] - self.pts[i]) / h - (2.0 * mi + mj) * (h / 6.0);
        let p = self.pts[i] + slope * u + mi * (u * u / 2.0) + (mj - mi) * (u * u * u / (6.0 * h));
        let d1 = slope + mi * u + (mj - mi) * (u * u / (2.0 * h));
        let d2 = mi + (mj - mi) * (u / h);
        (p, d1, d2)
    }
}

/// Row `i` of `R`: `(R x)_i = 6 (D_i - D_{i-1})` as (column, coefficient) pairs.
fn rhs_stencil(h: &[f64], i: usize) -> [(usize, f64); 3] {
    let n = h.len();
    let prev = (i + n - 1) % n;
    [
        (prev, 6.0 / h[prev]),
        (i, -6.0 / h[i] - 6.0 / h[prev]),
        ((i + 1) % n, 6.0 / h[i]),
    ]
}

/// Signed curvature from first and second derivatives.
fn curvature(d1: &Vector2<f64>, d2: &Vector2<f64>) -> f64 {
    (d1.x * d2.y - d1.y * d2.x) / d1.norm().powi(3)
}

/// A point of the node spline with its unit left normal and the offsets `[lo, hi]` along the
/// normal that keep it inside the corridor.
struct Gate {
    at: Point2<f64>,
    normal: Vector2<f64>,
    lo: f64,
    hi: f64,
    /// Curvature of the reference at `at`.
    kappa: f64,
}

impl Gate {
    /// How far the limit towards the inside of the bend reaches beyond `α κ = FOLD` (m).
    fn excess(&self) -> f64 {
        if self.kappa > 0.0 {
            (self.hi - FOLD / self.kappa).max(0.0)
        } else if self.kappa < 0.0 {
            (FOLD / self.kappa - self.lo).max(0.0)
        } else {
            0.0
        }
    }

    /// Cuts the limit towards the inside of the bend to `α κ ≤ FOLD`.
    fn cut(&mut self) {
        if self.kappa > 0.0 {
            self.hi = self.hi.min(FOLD / self.kappa);
        } else if self.kappa < 0.0 {
            self.lo = self.lo.max(FOLD / self.kappa);
        }
    }
}

/// `per_segment` gates along each segment of the `reference` spline, starting at its nodes. A
/// gate's limits are the offsets along its normal at which the lateral offset from the centreline,
/// measured as [`ClosedCurve::project`] does, reaches `-(w_right - half)` and `w_left - half`.
fn gates(cl: &Centreline, reference: &Spline, half: f64, per_segment: usize) -> Result<Vec<Gate>> {
    let mut hint = 0;
    (0..per_segment * reference.len())
        .map(|g| {
            let (at, d1, d2) = reference.sample(g, per_segment);
            let normal = Vector2::new(-d1.y, d1.x) / d1.norm();
            let mut limits = [0.0; 2];
            for (a, left) in limits.iter_mut().zip([false, true]) {
                for _ in 0..3 {
                    let pr = cl.curve.project_near(&(at + normal * *a), hint);
                    let (wr, wl) = cl.widths_at(pr.s);
                    *a += if left { wl - half } else { half - wr } - pr.lateral;
                    hint = pr.segment;
                }
            }
            let [lo, hi] = limits;
            if lo > hi {
                return Err(TrackError::Invalid {
                    what: "track width".into(),
                    message: format!(
                        "the corridor at s = {:.2} m is too narrow for car_width + 2 margin = \
                         {:.3} m; lower the raceline margin",
                        cl.curve.project(&at).s,
                        2.0 * half
                    ),
                });
            }
            Ok(Gate {
                at,
                normal,
                lo,
                hi,
                kappa: curvature(&d1, &d2),
            })
        })
        .collect()
}

/// Why the QP solver gave no solution.
#[derive(Debug, thiserror::Error)]
enum QpError {
    /// The solver refused the problem or its settings.
    #[error("{0}")]
    Setup(SolverError),
    /// The solver stopped without a solution.
    #[error("status {0}")]
    Status(SolverStatus),
}

/// Solves the QP linearised at `line` (the spline through the nodes `gates[k i]` shifted by
/// `α_i` along their normals, `k` gates per segment) for the total offsets `α`, and the solved
/// spline (on the knots of `line`).
fn solve_qp(
    line: &Spline,
    gates: &[Gate],
    kappa_max: Option<f64>,
) -> std::result::Result<(Vec<f64>, Spline), QpError> {
    let n = line.len();
    let per_segment = gates.len() / n;
    let node = |i: usize| &gates[per_segment * (i % n)];
    // variables z = [α, M_x, M_y]; M_c(i) is the column of coordinate c's M_i, and
    // κ_i = a_i M_y(i) - b_i M_x(i) with (a_i, b_i) = (x'_i, y'_i) / |v_i|³ of the current line
    let m_col = |c: usize, i: usize| (1 + c) * n + i % n;
    let ab: Vec<(f64, f64)> = (0..n)
        .map(|i| {
            let d1 = line.eval(i, 0.0).1;
            let c = d1.norm().powi(3);
            (d1.x / c, d1.y / c)
        })
        .collect();
    let mut p = Triplets::default();
    for (i, &(a, b)) in ab.iter().enumerate() {
        p.push(m_col(0, i), m_col(0, i), b * b);
        p.push(m_col(1, i), m_col(1, i), a * a);
        p.push(m_col(0, i), m_col(1, i), -a * b);
    }
    let mut a = Triplets::default();
    let mut rhs = Vec::new();
    for c in 0..2 {
        for i in 0..n {
            let row = rhs.len();
            let prev = (i + n - 1) % n;
            a.push(row, m_col(c, prev), line.h[prev]);
            a.push(row, m_col(c, i), 2.0 * (line.h[prev] + line.h[i]));
            a.push(row, m_col(c, i + 1), line.h[i]);
            let mut b = 0.0;
            for (j, coef) in rhs_stencil(&line.h, i) {
                a.push(row, j, -coef * node(j).normal[c]);
                b += coef * node(j).at[c];
            }
            rhs.push(b);
        }
    }
    for (g, gate) in gates.iter().enumerate() {
        // the spline at τ = u / h_i on segment i, r_i (1 - τ) + r_j τ + h_i² (c_i M_i + c_j M_j),
        // projected on the gate's normal relative to the gate
        let (i, tau) = (
            g / per_segment,
            (g % per_segment) as f64 / per_segment as f64,
        );
        let j = (i + 1) % n;
        let h2 = line.h[i] * line.h[i];
        let (ci, cj) = (
            h2 * (-tau / 3.0 + tau * tau / 2.0 - tau.powi(3) / 6.0),
            h2 * (tau.powi(3) - tau) / 6.0,
        );
        let mut row = vec![
            (i, (1.0 - tau) * gate.normal.dot(&node(i).normal)),
            (j, tau * gate.normal.dot(&node(j).normal)),
        ];
        for c in 0..2 {
            row.extend([
                (m_col(c, i), ci * gate.normal[c]),
                (m_col(c, j), cj * gate.normal[c]),
            ]);
        }
        let shift = gate
            .normal
            .dot(&(node(i).at.coords.lerp(&node(j).at.coords, tau) - gate.at.coords));
        for (sign, bound) in [(1.0, gate.hi - shift), (-1.0, shift - gate.lo)] {
            row.iter()
                .for_each(|&(col, v)| a.push(rhs.len(), col, sign * v));
            rhs.push(bound);
        }
    }
    if let Some(k) = kappa_max {
        for (i, &(ca, cb)) in ab.iter().enumerate() {
            for sign in [1.0, -1.0] {
                a.push(rhs.len(), m_col(1, i), sign * ca);
                a.push(rhs.len(), m_col(0, i), -sign * cb);
                rhs.push(k);
            }
        }
    }
    let cones = [ZeroConeT(2 * n), NonnegativeConeT(rhs.len() - 2 * n)];
    let settings = DefaultSettings {
        verbose: false,
        ..DefaultSettings::default()
    };
    let (p, a) = (p.into_csc(3 * n, 3 * n), a.into_csc(rhs.len(), 3 * n));
    let mut solver = DefaultSolver::new(&p, &vec![0.0; 3 * n], &a, &rhs, &cones, settings)
        .map_err(QpError::Setup)?;
    solver.solve();
    match solver.solution.status {
        SolverStatus::Solved | SolverStatus::AlmostSolved => {
            let x = &solver.solution.x;
            let spline = Spline {
                pts: (0..n).map(|i| node(i).at + node(i).normal * x[i]).collect(),
                h: line.h.clone(),
                m: (0..n)
                    .map(|i| Vector2::new(x[m_col(0, i)], x[m_col(1, i)]))
                    .collect(),
            };
            Ok((x[..n].to_vec(), spline))
        }
        status => Err(QpError::Status(status)),
    }
}

/// Sparse matrix entries collected as (row, column, value).
#[derive(Default)]
struct Triplets(Vec<usize>, Vec<usize>, Vec<f64>);

impl Triplets {
    fn push(&mut self, row: usize, col: usize, v: f64) {
        self.0.push(row);
        self.1.push(col);
        self.2.push(v);
    }

    fn into_csc(self, rows: usize, cols: usize) -> CscMatrix<f64> {
        CscMatrix::new_from_triplets(rows, cols, self.0, self.1, self.2)
    }
}

/// The mean of `c` over `s ± window`, sampled about `step / SMOOTHING` apart.
fn averaged(c: &ClosedCurve, s: f64, window: f64, step: f64) -> Point2<f64> {
    let k = (SMOOTHING * window / step).round().max(1.0) as i32;
    let sum: Vector2<f64> = (-k..=k)
        .map(|j| c.point_at(s + window * j as f64 / k as f64).coords)
        .sum();
    Point2::from(sum / (2 * k + 1) as f64)
}

/// The reference spline and its gates, `per_segment` a segment, cut by [`Gate::cut`]. Each node
/// averages the centreline over its own window, `step` at first; while gates have an
/// [`Gate::excess`], the windows of the nodes shaping their segments are widened and tapered, and
/// the round with the least excess in sum is kept.
fn reference(
    centreline: &Centreline,
    half: f64,
    per_segment: usize,
    params: &RacelineParams,
) -> Result<(Spline, Vec<Gate>)> {
    let c = &centreline.curve;
    let n = ((c.length() / params.step).round() as usize).max(8);
    let taper = TAPER * c.length() / n as f64;
    let mut windows = vec![params.step; n];
    let mut best: Option<(f64, Spline, Vec<Gate>)> = None;
    for round in 0..=WIDENINGS {
        let nodes = (0..n)
            .map(|i| averaged(c, c.length() * i as f64 / n as f64, windows[i], params.step))
            .collect();
        let built = Spline::new(nodes).and_then(|reference| {
            let gates = gates(centreline, &reference, half, per_segment)?;
            Ok((reference, gates))
        });
        // a widened reference can fail where the plain one did not: keep the best so far
        let (reference, gates) = match built {
            Ok(built) => built,
            Err(e) if round == 0 => return Err(e),
            Err(_) => break,
        };
        let excess: Vec<f64> = gates
            .chunks(per_segment)
            .map(|segment| segment.iter().map(Gate::excess).sum())
            .collect();
        let total: f64 = excess.iter().sum();
        if best.as_ref().is_none_or(|(least, ..)| total < *least) {
            best = Some((total, reference, gates));
        }
        if total == 0.0 {
            break;
        }
        // segment i is shaped by nodes i-1 … i+2
        let before = windows.clone();
        for i in (0..n).filter(|&i| excess[i] > 0.0) {
            for j in i + n - 1..=i + n + 2 {
                windows[j % n] = windows[j % n].max(before[i] * WIDEN);
            }
        }
        for k in 1..2 * n {
            windows[k % n] = windows[k % n].max(windows[(k - 1) % n] - taper);
        }
        for k in (0..2 * n - 1).rev() {
            windows[k % n] = windows[k % n].max(windows[(k + 1) % n] - taper);
        }
    }
    let (_, reference, mut gates) = best.expect("the first round always runs");
    for gate in &mut gates {
        gate.cut();
        if gate.lo > gate.hi {
            return Err(TrackError::Invalid {
                what: "track width".into(),
                message: format!(
                    "the corridor at s = {:.2} m lies beyond the centre of curvature of the \
                     averaged centreline, {:.3} m away; check the centreline there",
                    c.project(&gate.at).s,
                    1.0 / gate.kappa.abs()
                ),
            });
        }
    }
    Ok((reference, gates))
}

/// Optimises the minimum-curvature raceline inside the centreline's corridor and gives it the
/// speed profile of [`velocity_profile`].
pub fn min_curvature_raceline(
    centreline: &Centreline,
    params: &RacelineParams,
) -> Result<Raceline> {
    params.validate()?;
    let c = &centreline.curve;
    let half = params.car_width / 2.0 + params.margin;
    if let Some(i) =
        (0..c.len()).find(|&i| centreline.w_left[i] + centreline.w_right[i] < 2.0 * half)
    {
        return Err(TrackError::Invalid {
            what: "track width".into(),
            message: format!(
                "the track is {:.3} m wide at s = {:.2} m, narrower than car_width + 2 margin = \
                 {:.3} m; lower the raceline margin",
                centreline.w_left[i] + centreline.w_right[i],
                c.s_at_vertex(i),
                2.0 * half
            ),
        });
    }
    let per_segment = (params.step / OUTPUT_STEP).ceil() as usize;
    let (mut base, mut gates) = reference(centreline, half, per_segment, params)?;
    let kappa_max = params.kappa_max.is_finite().then_some(params.kappa_max);
    let solve = |base: &Spline, gates: &[Gate], stage: &str| {
        solve_qp(base, gates, kappa_max)
            .or_else(|_| solve_qp(base, gates, None))
            .map_err(|why| TrackError::Optimisation(format!("clarabel: {why} in {stage}")))
    };
    let (mut alpha, mut line) = solve(&base, &gates, "iteration 1")?;
    for iteration in 2..=params.max_iterations {
        // re-linearise at the new line, with its own chord lengths as knots
        base = Spline::new(line.pts.clone())?;
        let (new, solved) = solve(&base, &gates, &format!("iteration {iteration}"))?;
        let change = new
            .iter()
            .zip(&alpha)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max);
        (alpha, line) = (new, solved);
        if change < TOLERANCE {
            break;
        }
    }
    for repair in 1..=REPAIRS {
        // a vertex can still poke out where the centreline polyline kinks: tighten its gate
        let (mut hint, mut tightened) = (0, false);
        for (g, gate) in gates.iter_mut().enumerate() {
            let p = line.sample(g, per_segment).0;
            let pr = c.project_near(&p, hint);
            let (wr, wl) = centreline.widths_at(pr.s);
            let (left, right) = (pr.lateral - (wl - half), half - wr - pr.lateral);
            let offset = (p - gate.at).dot(&gate.normal);
            if left > 0.0 {
                gate.hi = gate.hi.min(offset) - left - REPAIR_EXTRA;
            }
            if right > 0.0 {
                gate.lo = gate.lo.max(offset) + right + REPAIR_EXTRA;
            }
            (hint, tightened) = (pr.segment, tightened || left > 0.0 || right > 0.0);
        }
        if !tightened {
            break;
        }
        line = solve(&base, &gates, &format!("repair {repair}"))?.1;
    }
    let (points, kappa): (Vec<_>, Vec<_>) = (0..gates.len())
        .map(|g| {
            let (p, d1, d2) = line.sample(g, per_segment);
            (p, curvature(&d1, &d2))
        })
        .unzip();
    let curve = ClosedCurve::new(points, "raceline")?;
    if curve.len() != kappa.len() {
        return Err(TrackError::Optimisation(
            "the raceline has coincident vertices".into(),
        ));
    }
    let (speed, accel) = velocity_profile(&curve, &kappa, params);
    Ok(Raceline {
        curve,
        kappa,
        speed,
        accel,
    })
}

/// Speed and longitudinal acceleration at each vertex of a closed line with curvature `kappa`
/// (one value per vertex), within `v_max`, `a_lat` and the friction ellipse with `a_long`.
///
/// # Panics
/// If `kappa` does not have one entry per vertex of `curve`.
pub fn velocity_profile(
    curve: &ClosedCurve,
    kappa: &[f64],
    params: &RacelineParams,
) -> (Vec<f64>, Vec<f64>) {
    let n = curve.len();
    assert_eq!(
        kappa.len(),
        n,
        "velocity_profile needs one curvature per vertex"
    );
    let ds: Vec<f64> = (0..n).map(|i| curve.segment_vector(i).norm()).collect();
    let mut v: Vec<f64> = kappa
        .iter()
        .map(|k| params.v_max.min((params.a_lat / k.abs()).sqrt()))
        .collect();
    let a_x = |v: f64, k: f64| {
        params.a_long
            * (1.0 - (v * v * k.abs() / params.a_lat).powi(2))
                .max(0.0)
                .sqrt()
    };
    let start = (0..n).min_by(|&i, &j| v[i].total_cmp(&v[j])).unwrap_or(0);
    for k in 0..2 * n {
        let i = (start + k) % n;
        let j = (i + 1) % n;
        v[j] = v[j].min((v[i] * v[i] + 2.0 * a_x(v[i], kappa[i]) * ds[i]).sqrt());
    }
    for k in 0..2 * n {
        let j = (start + 2 * n - k) % n;
        let i = (j + n - 1) % n;
        v[i] = v[i].min((v[j] * v[j] + 2.0 * a_x(v[j], kappa[j]) * ds[i]).sqrt());
    }
    let accel = (0..n)
        .map(|i| (v[(i + 1) % n].powi(2) - v[i].powi(2)) / (2.0 * ds[i]))
        .collect();
    (v, accel)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::PI;

    /// Counter-clockwise stadium: straights of length `straight` along y = ∓r joined by half
    /// circles of radius `r`, vertices about 0.2 m apart, free width `w` either side.
    fn stadium(straight: f64, r: f64, w: f64) -> Centreline {
        let (ns, na) = (
            (straight / 0.2).round() as usize,
            (PI * r / 0.2).round() as usize,
        );
        let mut rows = Vec::new();
        for (side, sign) in [(0.0, 1.0), (1.0, -1.0)] {
            for k in 0..ns {
                let x = -straight / 2.0 + straight * k as f64 / ns as f64;
                rows.push([sign * x, -sign * r, w, w]);
            }
            for k in 0..na {
                let a = -PI / 2.0 + PI * (k as f64 / na as f64 + side);
                rows.push([sign * straight / 2.0 + r * a.cos(), r * a.sin(), w, w]);
            }
        }
        Centreline::new(&rows, "stadium").unwrap()
    }

    /// `∫ κ² ds` along a closed curve.
    fn bending(curve: &ClosedCurve, kappa: &[f64]) -> f64 {
        (0..curve.len())
            .map(|i| kappa[i].powi(2) * curve.segment_vector(i).norm())
            .sum()
    }

    /// Asserts every raceline vertex lies inside the corridor; returns the largest |offset|.
    fn assert_inside(cl: &Centreline, line: &Raceline, params: &RacelineParams) -> f64 {
        let half = params.car_width / 2.0 + params.margin;
        let mut widest: f64 = 0.0;
        for p in line.curve.points() {
            let pr = cl.curve.project(p);
            let (wr, wl) = cl.widths_at(pr.s);
            assert!(
                pr.lateral >= -(wr - half) - 1e-3 && pr.lateral <= wl - half + 1e-3,
                "offset {} at s = {} outside [{}, {}]",
                pr.lateral,
                pr.s,
                half - wr,
                wl - half
            );
            widest = widest.max(pr.lateral.abs());
        }
        widest
    }

    #[test]
    fn mincurv_oval_line_is_flatter_and_inside_the_walls() {
        let params = RacelineParams::default();
        let cl = stadium(20.0, 5.0, 1.0);
        let line = min_curvature_raceline(&cl, &params).unwrap();
        let before = bending(&cl.curve, &cl.curve.vertex_curvatures());
        let after = bending(&line.curve, &line.kappa);
        assert!(after < 0.9 * before, "∫κ² {after} vs centreline {before}");
        let widest = assert_inside(&cl, &line, &params);
        // the corridor allows 1 − 0.155 − margin
        assert!(
            widest > 0.8 - params.margin,
            "the line should use the corridor, widest offset {widest}"
        );
    }

    #[test]
    fn mincurv_circle_stays_a_circle() {
        let params = RacelineParams::default();
        let cl = stadium(0.0, 5.0, 1.0);
        let line = min_curvature_raceline(&cl, &params).unwrap();
        assert_inside(&cl, &line, &params);
        let mean = line.kappa.iter().sum::<f64>() / line.kappa.len() as f64;
        assert!(mean > 1.0 / 6.0 && mean < 1.0 / 4.0, "mean κ {mean}");
        for &k in &line.kappa {
            assert!((k - mean).abs() < 0.01 * mean, "κ {k} vs mean {mean}");
        }
    }

    #[test]
    fn mincurv_sharp_corners_give_no_cusp() {
        // a square with sharp corners: averaging over ±step rounds them to a radius well below
        // the corridor's inner width of 1.5 - 0.455 m, so the normals would cross
        let side = 12.0;
        let per_side = (side / 0.2) as usize;
        let corners = [(0.0, 0.0), (side, 0.0), (side, side), (0.0, side)];
        let rows: Vec<[f64; 4]> = (0..4)
            .flat_map(|c| {
                let ((x0, y0), (x1, y1)) = (corners[c], corners[(c + 1) % 4]);
                (0..per_side).map(move |k| {
                    let t = k as f64 / per_side as f64;
                    [x0 + (x1 - x0) * t, y0 + (y1 - y0) * t, 1.5, 1.5]
                })
            })
            .collect();
        let cl = Centreline::new(&rows, "square").unwrap();
        let params = RacelineParams::default();
        let line = min_curvature_raceline(&cl, &params).unwrap();
        assert_inside(&cl, &line, &params);
        // the 2.09 m corridor allows the corners a radius of 2.09 / (1 - cos 45°) = 7.1 m
        let sharpest = line.kappa.iter().fold(0.0, |m: f64, k| m.max(k.abs()));
        assert!(sharpest < 0.25, "max |κ| {sharpest}");
    }

    #[test]
    fn mincurv_gates_are_cut_short_of_the_centre_of_curvature() {
        let gate = |kappa: f64| Gate {
            at: Point2::origin(),
            normal: Vector2::y(),
            lo: -0.6,
            hi: 0.6,
            kappa,
        };
        // a left bend of radius 0.5 m: the left limit stops at 0.8 × 0.5 m
        let mut left = gate(2.0);
        assert!((left.excess() - 0.2).abs() < 1e-12);
        left.cut();
        assert_eq!((left.lo, left.hi, left.excess()), (-0.6, 0.4, 0.0));
        // a right bend, mirrored
        let mut right = gate(-2.0);
        assert!((right.excess() - 0.2).abs() < 1e-12);
        right.cut();
        assert_eq!((right.lo, right.hi, right.excess()), (-0.4, 0.6, 0.0));
        // a gentle bend and a straight keep their limits
        for kappa in [0.5, 0.0] {
            let mut g = gate(kappa);
            g.cut();
            assert_eq!((g.lo, g.hi, g.excess()), (-0.6, 0.6, 0.0));
        }
    }

    #[test]
    fn mincurv_infeasible_curvature_limit_is_dropped() {
        let cl = stadium(0.0, 5.0, 1.0);
        let strict = RacelineParams {
            kappa_max: 0.1,
            ..RacelineParams::default()
        };
        let line = min_curvature_raceline(&cl, &strict).unwrap();
        let free = min_curvature_raceline(&cl, &RacelineParams::default()).unwrap();
        assert!((line.curve.length() - free.curve.length()).abs() < 1e-6);
        assert_inside(&cl, &line, &strict);
    }

    #[test]
    fn mincurv_speed_profile_respects_the_limits_on_a_long_oval() {
        let params = RacelineParams::default();
        let line = min_curvature_raceline(&stadium(60.0, 3.0, 1.0), &params).unwrap();
        for i in 0..line.curve.len() {
            let (v, k, a) = (line.speed[i], line.kappa[i], line.accel[i]);
            assert!(
                v <= params.v_max + 1e-9 && v * v * k.abs() <= params.a_lat + 1e-6,
                "{v} {k}"
            );
            assert!(a.abs() <= params.a_long + 1e-6, "accel {a} at vertex {i}");
        }
        let fastest = line.speed.iter().cloned().fold(0.0, f64::max);
        let slowest = line.speed.iter().cloned().fold(f64::INFINITY, f64::min);
        assert!((fastest - params.v_max).abs() < 1e-9 && slowest < 0.8 * params.v_max);
        assert!(line.lap_time().is_finite());
    }

    #[test]
    fn mincurv_speed_on_a_circle_is_the_lateral_limit() {
        let params = RacelineParams::default();
        for r in [2.0, 10.0] {
            let pts = (0..500)
                .map(|i| {
                    let a = i as f64 / 500.0 * 2.0 * PI;
                    Point2::new(r * a.cos(), r * a.sin())
                })
                .collect();
            let curve = ClosedCurve::new(pts, "circle").unwrap();
            let (v, a) = velocity_profile(&curve, &vec![1.0 / r; 500], &params);
            let expected = params.v_max.min((params.a_lat * r).sqrt());
            assert!(
                v.iter().all(|v| (v - expected).abs() < 1e-9),
                "r {r}: {v:?}"
            );
            assert!(a.iter().all(|a| a.abs() < 1e-9));
        }
    }

    #[test]
    fn mincurv_rejects_narrow_tracks_and_bad_params() {
        let err = min_curvature_raceline(&stadium(20.0, 5.0, 0.2), &RacelineParams::default())
            .unwrap_err()
            .to_string();
        assert!(err.contains("0.400 m wide at s = 0.00 m"), "{err}");
        let params = RacelineParams {
            a_long: 0.0,
            ..RacelineParams::default()
        };
        let err = params.validate().unwrap_err().to_string();
        assert!(
            err.contains("raceline.a_long") && err.contains("> 0"),
            "{err}"
        );
        let params: RacelineParams = serde_yaml::from_str("v_max: 5.0").unwrap();
        assert_eq!(
            params,
            RacelineParams {
                v_max: 5.0,
                ..RacelineParams::default()
            }
        );
        assert!(serde_yaml::from_str::<RacelineParams>("vmax: 5.0").is_err());
    }

    #[test]
    fn mincurv_paper_maps() {
        let dir = crate::files::shared_reference("tracks").unwrap_or_else(|e| panic!("{e}"));
        for name in ["f1_esp", "f1_gbr"] {
            let path = dir.join(format!("{name}_centerline.csv"));
            let text = std::fs::read_to_string(&path).unwrap();
            let rows: Vec<[f64; 4]> = text
                .lines()
                .filter(|l| !l.trim().is_empty())
                .map(|l| {
                    let v: Vec<f64> = l.split(',').map(|c| c.trim().parse().unwrap()).collect();
                    [v[0], v[1], v[2], v[3]]
                })
                .collect();
            let cl = Centreline::new(&rows, &path.display().to_string()).unwrap();
            let params = RacelineParams::default();
            let started = std::time::Instant::now();
            let line = min_curvature_raceline(&cl, &params).unwrap();
            let elapsed = started.elapsed();
            let before = bending(&cl.curve, &cl.curve.vertex_curvatures());
            let after = bending(&line.curve, &line.kappa);
            eprintln!(
                "{name}: {elapsed:?}; centreline {:.2} m, raceline {:.2} m, lap {:.2} s, \
                 ∫κ² ds {after:.2} (centreline {before:.2}), max |κ| {:.3}",
                cl.curve.length(),
                line.curve.length(),
                line.lap_time(),
                line.kappa.iter().fold(0.0, |m: f64, k| m.max(k.abs()))
            );
            assert_inside(&cl, &line, &params);
            assert!(after < before);
            assert!(line.lap_time().is_finite() && line.lap_time() > 0.0);
            assert!(line
                .speed
                .iter()
                .all(|&v| v > 0.0 && v <= params.v_max + 1e-9));
        }
    }
}
