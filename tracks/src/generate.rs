//! Procedural generator of random race circuits, for training on tracks the agent has never seen.
//!
//! Method, per attempt:
//! 1. **Polygon.** `k` vertices at increasing angles around the origin (evenly spread, each jittered
//!    by up to ±30 % of the spacing) with random radii in `[0.25, 1]`. Sorted by angle with gaps
//!    below π they form a star-shaped polygon, which cannot intersect itself; vertices pulled in
//!    between outer neighbours become right-hand bends. It is scaled to perimeter `params.length`.
//! 2. **Corners.** Every vertex is rounded by the circular arc tangent to both edges, with a random
//!    radius in `[1.1, 4] × min_radius` that leaves each edge at least half for its other end; the
//!    remaining edge pieces are straights. (An attempt whose edges are too short is rejected.)
//! 3. **Smoothing.** The curve is resampled every `≈ params.spacing` of arc length and averaged over
//!    a window of `min_radius` (moving average), which ramps the curvature in and out of each arc
//!    like a transition curve, then scaled about the origin to length `params.length` (both steps
//!    shorten the curve, so the scale only widens the radii).
//! 4. **Checks.** The attempt is rejected unless (a) the Menger curvature radius at every point is at
//!    least `min_radius`; (b) points further apart along the track than a U-turn whose legs are
//!    `width + 1 m` apart (arc `π (width + 1) / 2`) are at least `width + 1 m` apart, so walls of
//!    different parts of the track keep a 1 m gap; (c) the two wall polylines do not cross each
//!    other or themselves.
//! 5. **Start.** The points are rotated so that `s = 0` begins the 20 % of the lap with the least
//!    squared curvature: the starting grid lines up ahead of `s = 0` on that gentle stretch.
//!
//! Attempt `a` draws from `ChaCha8Rng::seed_from_u64(seed)` on stream `a`, so a seed gives the same
//! track everywhere and each attempt is reproducible on its own. After [`MAX_ATTEMPTS`] rejections
//! the generator gives up with an error. Walls are [`wall_polylines`], the left one inside since
//! tracks run counter-clockwise.

use crate::error::{Result, TrackError};
use crate::path::{menger_curvature, Centreline, ClosedCurve};
use nalgebra::{Point2, Rotation2, Vector2};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use std::f64::consts::{PI, TAU};

/// Attempts before [`generate_track`] gives up.
pub const MAX_ATTEMPTS: u64 = 300;
/// Gap kept between the walls of non-adjacent parts of the track (m).
const WALL_GAP: f64 = 1.0;
/// How far `min_radius` must exceed half the width so that the inner wall cannot fold (m).
const RADIUS_MARGIN: f64 = 0.3;
/// Fraction of the lap after `s = 0` chosen to be gentle (the starting grid).
const GRID_FRACTION: f64 = 0.2;
/// Corner radii are drawn from `[MIN, MAX] × min_radius`; `MIN > 1` leaves room for the smoothing.
const CORNER_RADIUS_FACTORS: (f64, f64) = (1.1, 4.0);
/// Half-width of the moving-average window, as a fraction of `min_radius`.
const SMOOTHING_FACTOR: f64 = 0.5;
/// Most points a generated centreline may have (bounds `spacing` from below).
const MAX_POINTS: f64 = 20_000.0;
/// Arc sampling step before resampling, as a fraction of `spacing`.
const ARC_STEP_FACTOR: f64 = 0.25;

/// Shape of the generated circuits.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct GeneratorParams {
    /// Target centreline length (m); the result is within ±5 %.
    pub length: f64,
    /// Total track width (m), split equally to either side of the centreline.
    pub width: f64,
    /// Minimum corner radius of the centreline (m); must exceed `width / 2 + 0.3`.
    pub min_radius: f64,
    /// Spacing of the output points (m).
    pub spacing: f64,
}

impl Default for GeneratorParams {
    fn default() -> Self {
        Self {
            length: 80.0,
            width: 2.2,
            min_radius: 2.5,
            spacing: 0.2,
        }
    }
}

impl GeneratorParams {
    /// The shortest `length` these `width` and `min_radius` allow: room for two and a half full turns
    /// at the minimum radius and for twelve track widths plus wall gaps.
    pub fn min_length(&self) -> f64 {
        (5.0 * PI * self.min_radius).max(12.0 * (self.width + WALL_GAP))
    }

    /// Checks that every value is positive and finite, `min_radius > width / 2 + 0.3`,
    /// `length >= min_length()` and `length / 20000 <= spacing <= min_radius / 4`.
    pub fn validate(&self) -> Result<()> {
        let invalid = |field: &str, message: String| {
            Err(TrackError::Invalid {
                what: format!("generator {field}"),
                message,
            })
        };
        for (field, v) in [
            ("length", self.length),
            ("width", self.width),
            ("min_radius", self.min_radius),
            ("spacing", self.spacing),
        ] {
            if !(v.is_finite() && v > 0.0) {
                return invalid(field, format!("must be positive and finite (got {v})"));
            }
        }
        let r_lo = self.width / 2.0 + RADIUS_MARGIN;
        if self.min_radius <= r_lo {
            return invalid(
                "min_radius",
                format!(
                    "must exceed width / 2 + {RADIUS_MARGIN} = {r_lo} m so the inner wall cannot fold (got {} m)",
                    self.min_radius
                ),
            );
        }
        let l_lo = self.min_length();
        if self.length < l_lo {
            return invalid(
                "length",
                format!(
                    "must be at least {l_lo:.1} m for width {} m and min_radius {} m (got {} m)",
                    self.width, self.min_radius, self.length
                ),
            );
        }
        let (s_lo, s_hi) = (self.length / MAX_POINTS, self.min_radius / 4.0);
        if !(s_lo..=s_hi).contains(&self.spacing) {
            return invalid(
                "spacing",
                format!(
                    "must be in [length / {MAX_POINTS}, min_radius / 4] = [{s_lo}, {s_hi}] m (got {} m)",
                    self.spacing
                ),
            );
        }
        Ok(())
    }
}

/// A random closed circuit for `seed`: counter-clockwise, not self-intersecting, `s = 0` at the start
/// of a gentle stretch, length within ±5 % of `params.length`, points `≈ params.spacing` apart,
/// `width / 2` free to either side. The same seed and parameters always give the same track. Fails
/// on invalid parameters or when no attempt passes the checks (see the module docs).
pub fn generate_track(seed: u64, params: &GeneratorParams) -> Result<Centreline> {
    generate(seed, params).map(|(centreline, _)| centreline)
}

/// [`generate_track`], also returning the number of attempts used.
fn generate(seed: u64, params: &GeneratorParams) -> Result<(Centreline, u64)> {
    params.validate()?;
    for attempt in 0..MAX_ATTEMPTS {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        rng.set_stream(attempt);
        if let Some(centreline) = try_generate(&mut rng, params) {
            return Ok((centreline, attempt + 1));
        }
    }
    Err(TrackError::Invalid {
        what: format!("generated track (seed {seed})"),
        message: format!(
            "no circuit met min_radius {} m and the wall clearance in {MAX_ATTEMPTS} attempts; \
             raise length or lower width or min_radius",
            params.min_radius
        ),
    })
}

/// One attempt: a candidate circuit, or `None` when it fails a check.
fn try_generate(rng: &mut ChaCha8Rng, p: &GeneratorParams) -> Option<Centreline> {
    let rounded =
        ClosedCurve::new(round_corners(&polygon(rng, p), rng, p)?, "generated track").ok()?;
    let n = (p.length / p.spacing).round() as usize;
    let step = rounded.length() / n as f64;
    let even: Vec<Point2<f64>> = (0..n).map(|k| rounded.point_at(k as f64 * step)).collect();
    let smooth = moving_average(
        &even,
        (SMOOTHING_FACTOR * p.min_radius / step).round() as usize,
    );
    let length: f64 = (0..n)
        .map(|i| (smooth[(i + 1) % n] - smooth[i]).norm())
        .sum();
    let pts: Vec<Point2<f64>> = smooth.iter().map(|q| q * (p.length / length)).collect();
    let kappa: Vec<f64> = (0..n)
        .map(|i| menger_curvature(&pts[(i + n - 1) % n], &pts[i], &pts[(i + 1) % n]))
        .collect();
    if kappa.iter().any(|k| k.abs() * p.min_radius > 1.0) || !clear(&pts, p) {
        return None;
    }
    let start = gentlest_start(&kappa, (GRID_FRACTION * n as f64).round() as usize);
    let half = p.width / 2.0;
    let rows: Vec<[f64; 4]> = (0..n)
        .map(|k| {
            let q = pts[(start + k) % n];
            [q.x, q.y, half, half]
        })
        .collect();
    let centreline = Centreline::new(&rows, "generated track").ok()?;
    (!walls_cross(&wall_polylines(&centreline))).then_some(centreline)
}

/// Star-shaped polygon around the origin with perimeter `p.length`.
fn polygon(rng: &mut ChaCha8Rng, p: &GeneratorParams) -> Vec<Point2<f64>> {
    // About one vertex per 3.5 min_radius of track, within 5 ..= 16.
    let typical = (p.length / (3.5 * p.min_radius)).round().clamp(5.0, 16.0) as usize;
    let k = rng.random_range(typical.saturating_sub(2).max(5)..=typical + 2);
    let phase = rng.random_range(0.0..TAU);
    let star: Vec<Point2<f64>> = (0..k)
        .map(|i| {
            let a = phase + TAU * (i as f64 + rng.random_range(-0.3..0.3)) / k as f64;
            let r = rng.random_range(0.25..1.0);
            Point2::new(r * a.cos(), r * a.sin())
        })
        .collect();
    let perimeter: f64 = (0..k).map(|i| (star[(i + 1) % k] - star[i]).norm()).sum();
    star.iter().map(|q| q * (p.length / perimeter)).collect()
}

/// Replaces every vertex of the closed polygon by a circular arc tangent to both edges (random
/// radius, see [`CORNER_RADIUS_FACTORS`]) sampled every `ARC_STEP_FACTOR × spacing`; the straight
/// pieces in between are implied. `None` when an edge is too short for the smallest radius.
fn round_corners(
    poly: &[Point2<f64>],
    rng: &mut ChaCha8Rng,
    p: &GeneratorParams,
) -> Option<Vec<Point2<f64>>> {
    let n = poly.len();
    let (r_lo, r_hi) = (
        CORNER_RADIUS_FACTORS.0 * p.min_radius,
        CORNER_RADIUS_FACTORS.1 * p.min_radius,
    );
    let mut out = Vec::new();
    for i in 0..n {
        let (a, b, c) = (poly[(i + n - 1) % n], poly[i], poly[(i + 1) % n]);
        let (d_in, d_out) = ((b - a).normalize(), (c - b).normalize());
        let turn = d_in.perp(&d_out).atan2(d_in.dot(&d_out));
        let tan_half = (turn.abs() / 2.0).tan();
        // The tangent points r tan(|turn| / 2) from the vertex must stay within half of each edge.
        let r_fit = (b - a).norm().min((c - b).norm()) / 2.0 / tan_half;
        if r_fit < r_lo {
            return None;
        }
        // log-uniform: tight corners as likely as sweeping ones
        let r = r_lo * (r_fit.min(r_hi) / r_lo).powf(rng.random::<f64>());
        let start = b - d_in * (r * tan_half);
        let centre = start + Vector2::new(-d_in.y, d_in.x) * (r * turn.signum());
        let steps = (r * turn.abs() / (ARC_STEP_FACTOR * p.spacing))
            .ceil()
            .max(1.0) as usize;
        out.extend(
            (0..=steps).map(|j| {
                centre + Rotation2::new(turn * j as f64 / steps as f64) * (start - centre)
            }),
        );
    }
    Some(out)
}

/// Cyclic moving average of each point with its `m` neighbours either side.
fn moving_average(pts: &[Point2<f64>], m: usize) -> Vec<Point2<f64>> {
    let n = pts.len();
    let w = (2 * m + 1) as f64;
    (0..n)
        .map(|i| {
            let sum: Vector2<f64> = (0..=2 * m)
                .map(|k| {
                    pts[(i as isize + k as isize - m as isize).rem_euclid(n as isize) as usize]
                        .coords
                })
                .sum();
            Point2::from(sum / w)
        })
        .collect()
}

/// Whether points further apart along the track than a U-turn of diameter `width + 1 m` keep at
/// least that distance (evenly spaced points assumed).
fn clear(pts: &[Point2<f64>], p: &GeneratorParams) -> bool {
    let n = pts.len();
    let gap = p.width + WALL_GAP;
    let adjacent = (PI * gap / 2.0 / (p.length / n as f64)).ceil() as usize;
    let ranges: Vec<(f64, f64)> = pts.iter().map(|q| (q.x, q.x + gap)).collect();
    !any_overlapping_pair(&ranges, |i, j| {
        let d = i.abs_diff(j);
        d.min(n - d) >= adjacent && (pts[i] - pts[j]).norm() < gap
    })
}

/// Start index of the `window` consecutive points (cyclically) with the least `Σ κ²`.
fn gentlest_start(kappa: &[f64], window: usize) -> usize {
    let n = kappa.len();
    let mut cost: f64 = kappa.iter().cycle().take(window).map(|k| k * k).sum();
    let mut best = (cost, 0);
    for i in 1..n {
        cost += kappa[(i + window - 1) % n].powi(2) - kappa[i - 1].powi(2);
        if cost < best.0 {
            best = (cost, i);
        }
    }
    best.1
}

/// Whether any two non-neighbouring segments of the closed polylines `walls` properly cross.
fn walls_cross(walls: &[Vec<Point2<f64>>]) -> bool {
    let segs: Vec<(usize, usize, Point2<f64>, Point2<f64>)> = walls
        .iter()
        .enumerate()
        .flat_map(|(w, pts)| (0..pts.len()).map(move |i| (w, i, pts[i], pts[(i + 1) % pts.len()])))
        .collect();
    let ranges: Vec<(f64, f64)> = segs
        .iter()
        .map(|s| (s.2.x.min(s.3.x), s.2.x.max(s.3.x)))
        .collect();
    let orient = |a: Point2<f64>, b: Point2<f64>, c: Point2<f64>| (b - a).perp(&(c - a));
    any_overlapping_pair(&ranges, |i, j| {
        let ((wa, ia, a, b), (wb, ib, c, d)) = (segs[i], segs[j]);
        let d_idx = ia.abs_diff(ib);
        let neighbours = wa == wb && (d_idx <= 1 || d_idx + 1 == walls[wa].len());
        !neighbours
            && orient(a, b, c) * orient(a, b, d) < 0.0
            && orient(c, d, a) * orient(c, d, b) < 0.0
    })
}

/// Whether `hit(i, j)` holds for some pair of items whose x-ranges `(lo, hi)` overlap (sort and
/// sweep, so only nearby pairs are tested).
fn any_overlapping_pair(ranges: &[(f64, f64)], hit: impl Fn(usize, usize) -> bool) -> bool {
    let mut order: Vec<usize> = (0..ranges.len()).collect();
    order.sort_by(|&a, &b| ranges[a].0.total_cmp(&ranges[b].0));
    order.iter().enumerate().any(|(k, &i)| {
        order[k + 1..]
            .iter()
            .take_while(|&&j| ranges[j].0 <= ranges[i].1)
            .any(|&j| hit(i, j))
    })
}

/// The walls of a centreline as `[left, right]` closed polylines, one point per centreline vertex,
/// the first point **not** repeated at the end (the segment last → first closes each wall).
/// Point `i` is `p_i + n_i w_left_i` (left) or `p_i - n_i w_right_i` (right), with `n_i` the unit
/// left normal at vertex `i`: the normalised average of the adjacent segments' left normals.
pub fn wall_polylines(centreline: &Centreline) -> Vec<Vec<Point2<f64>>> {
    let curve = &centreline.curve;
    let n = curve.len();
    let segment_normal = |i: usize| {
        let d = curve.segment_vector(i);
        Vector2::new(-d.y, d.x) / d.norm()
    };
    let normals: Vec<Vector2<f64>> = (0..n)
        .map(|i| {
            (segment_normal(i + n - 1) + segment_normal(i))
                .try_normalize(1e-12)
                .unwrap_or_else(|| segment_normal(i))
        })
        .collect();
    let pts = curve.points();
    vec![
        (0..n)
            .map(|i| pts[i] + normals[i] * centreline.w_left[i])
            .collect(),
        (0..n)
            .map(|i| pts[i] - normals[i] * centreline.w_right[i])
            .collect(),
    ]
}

#[cfg(test)]
mod tests {
    use super::*;

    fn signed_area(pts: &[Point2<f64>]) -> f64 {
        let n = pts.len();
        (0..n)
            .map(|i| pts[i].coords.perp(&pts[(i + 1) % n].coords))
            .sum::<f64>()
            / 2.0
    }

    /// Brute-force check, independent of the generator's sweep: do two non-neighbouring segments of
    /// the closed polylines cross or touch (an end point within 1 µm of the other segment)?
    fn any_intersection(walls: &[Vec<Point2<f64>>]) -> bool {
        let cross = |o: Point2<f64>, a: Point2<f64>, b: Point2<f64>| {
            (a.x - o.x) * (b.y - o.y) - (a.y - o.y) * (b.x - o.x)
        };
        let dist = |q: Point2<f64>, a: Point2<f64>, b: Point2<f64>| {
            let t = ((q - a).dot(&(b - a)) / (b - a).norm_squared()).clamp(0.0, 1.0);
            (q - (a + (b - a) * t)).norm()
        };
        let segs: Vec<(usize, usize, Point2<f64>, Point2<f64>)> = walls
            .iter()
            .enumerate()
            .flat_map(|(w, p)| (0..p.len()).map(move |i| (w, i, p[i], p[(i + 1) % p.len()])))
            .collect();
        segs.iter().enumerate().any(|(k, &(wa, ia, a, b))| {
            segs[k + 1..].iter().any(|&(wb, ib, c, d)| {
                let n = walls[wa].len();
                if wa == wb && (ia.abs_diff(ib) <= 1 || ia.abs_diff(ib) == n - 1) {
                    return false;
                }
                let crossing =
                    cross(a, b, c) * cross(a, b, d) < 0.0 && cross(c, d, a) * cross(c, d, b) < 0.0;
                let touching = dist(a, c, d)
                    .min(dist(b, c, d))
                    .min(dist(c, a, b))
                    .min(dist(d, a, b))
                    < 1e-6;
                crossing || touching
            })
        })
    }

    #[test]
    fn same_seed_same_track_different_seed_different_track() {
        let p = GeneratorParams::default();
        let bits = |c: &Centreline| -> Vec<(u64, u64)> {
            c.curve
                .points()
                .iter()
                .map(|q| (q.x.to_bits(), q.y.to_bits()))
                .collect()
        };
        let a = generate_track(7, &p).unwrap();
        let b = generate_track(7, &p).unwrap();
        let c = generate_track(8, &p).unwrap();
        assert_eq!(bits(&a), bits(&b));
        assert_ne!(bits(&a), bits(&c));
    }

    #[test]
    fn generated_tracks_meet_the_constraints() {
        let p = GeneratorParams::default();
        let gap = p.width + WALL_GAP;
        for seed in 0..50 {
            let (c, attempts) = generate(seed, &p).unwrap();
            assert!(attempts <= MAX_ATTEMPTS);
            let pts = c.curve.points();
            let n = pts.len();
            assert!(
                (c.curve.length() / p.length - 1.0).abs() < 0.05,
                "seed {seed}: length {}",
                c.curve.length()
            );
            for i in 0..n {
                let ds = c.curve.segment_vector(i).norm();
                assert!(
                    (ds / p.spacing - 1.0).abs() < 0.2,
                    "seed {seed}: spacing {ds}"
                );
            }
            let kappa = c.curve.vertex_curvatures();
            let k_max = kappa.iter().fold(0.0f64, |m, k| m.max(k.abs()));
            assert!(
                k_max <= 1.0 / p.min_radius + 1e-9,
                "seed {seed}: radius {}",
                1.0 / k_max
            );
            assert!(signed_area(pts) > 0.0, "seed {seed}: clockwise");
            assert!(c
                .w_left
                .iter()
                .chain(&c.w_right)
                .all(|&w| w == p.width / 2.0));
            let walls = wall_polylines(&c);
            assert!(!any_intersection(&walls), "seed {seed}: walls intersect");
            // centreline clearance between parts more than a U-turn apart along the track
            let adjacent = (PI * gap / 2.0 / p.spacing * 1.05).ceil() as usize;
            for i in 0..n {
                for j in i + 1..n {
                    let d = (pts[i] - pts[j]).norm();
                    let apart = (j - i).min(n + i - j) >= adjacent;
                    assert!(
                        !apart || d >= gap,
                        "seed {seed}: points {i} and {j} only {d} m apart"
                    );
                }
            }
            // the starting grid (first 20 %) is gentler than the lap on average
            let mean_sq = |k: &[f64]| k.iter().map(|k| k * k).sum::<f64>() / k.len() as f64;
            assert!(
                mean_sq(&kappa[..n / 5]) < mean_sq(&kappa),
                "seed {seed}: start not gentle"
            );
        }
    }

    #[test]
    fn walls_of_a_circle() {
        let r = 5.0;
        let rows: Vec<[f64; 4]> = (0..100)
            .map(|i| {
                let a = i as f64 / 100.0 * TAU;
                [r * a.cos(), r * a.sin(), 0.5, 1.0]
            })
            .collect();
        let c = Centreline::new(&rows, "circle").unwrap();
        let walls = wall_polylines(&c);
        assert_eq!(walls.len(), 2);
        assert!(walls.iter().all(|w| w.len() == 100));
        assert!(walls[0]
            .iter()
            .all(|q| (q.coords.norm() - (r - 1.0)).abs() < 1e-12));
        assert!(walls[1]
            .iter()
            .all(|q| (q.coords.norm() - (r + 0.5)).abs() < 1e-12));
        assert!(
            (walls[0][0] - walls[0][99]).norm() > 0.1,
            "first point is not repeated"
        );
    }

    #[test]
    fn invalid_params_name_the_field() {
        let d = GeneratorParams::default();
        let cases = [
            (
                GeneratorParams {
                    length: -1.0,
                    ..d.clone()
                },
                "length",
            ),
            (
                GeneratorParams {
                    length: 20.0,
                    ..d.clone()
                },
                "length",
            ),
            (
                GeneratorParams {
                    width: 0.0,
                    ..d.clone()
                },
                "width",
            ),
            (
                GeneratorParams {
                    min_radius: 1.3,
                    ..d.clone()
                },
                "min_radius",
            ),
            (
                GeneratorParams {
                    spacing: f64::NAN,
                    ..d.clone()
                },
                "spacing",
            ),
            (
                GeneratorParams {
                    spacing: 1.0,
                    ..d.clone()
                },
                "spacing",
            ),
        ];
        for (p, field) in cases {
            let err = generate_track(0, &p).unwrap_err().to_string();
            assert!(err.contains(&format!("generator {field}")), "{err}");
        }
        assert!(d.validate().is_ok());
    }

    #[test]
    fn params_from_yaml() {
        let p: GeneratorParams = serde_yaml::from_str("length: 60.0").unwrap();
        assert_eq!(
            p,
            GeneratorParams {
                length: 60.0,
                ..GeneratorParams::default()
            }
        );
        assert!(serde_yaml::from_str::<GeneratorParams>("lenght: 60.0").is_err());
    }
}
