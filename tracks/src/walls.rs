//! Track walls as polylines in world coordinates, held in one parry2d [`Polyline`] with its BVH.
//!
//! From a map image the walls are the iso-line between free and occupied pixels, traced by marching
//! squares on the pixel centres: each boundary vertex sits on the midpoint between a free and an
//! occupied pixel centre, i.e. on the pixel edge. The resulting closed loops are simplified with
//! Douglas–Peucker to half a pixel, the accuracy of the map itself. Ray casts and footprint tests
//! against them are exact (up to `f32`, ~1 µm at track scale).

use crate::map::OccupancyMap;
use nalgebra::{Isometry2, Point2, Vector2};
use parry2d::query::details::intersection_test_cuboid_segment;
use parry2d::query::{Ray, RayCast};
use parry2d::shape::{Cuboid, Polyline};
use std::collections::HashMap;

/// The walls of a track.
#[derive(Clone)]
pub struct Walls {
    polyline: Polyline,
    loops: Vec<Vec<Point2<f64>>>,
    clearance: ClearanceGrid,
}

/// Lower bounds of the distance to the nearest wall over the cells of a uniform grid: the distance
/// from the cell centre minus half the cell diagonal. A footprint whose circumscribed circle fits
/// in its cell's clearance cannot touch a wall, which settles most footprint tests without a BVH
/// query.
#[derive(Clone, Debug)]
struct ClearanceGrid {
    origin: Point2<f32>,
    cell: f32,
    nx: usize,
    ny: usize,
    lower: Vec<f32>,
}

impl ClearanceGrid {
    /// Grid cell size (m).
    const CELL: f32 = 0.25;

    fn new(polyline: &Polyline) -> Self {
        use parry2d::query::PointQuery;
        if polyline.num_segments() == 0 {
            return Self {
                origin: Point2::origin(),
                cell: Self::CELL,
                nx: 0,
                ny: 0,
                lower: Vec::new(),
            };
        }
        let aabb = polyline.local_aabb();
        let cell = Self::CELL;
        let origin = aabb.mins - Vector2::new(cell, cell);
        let nx = ((aabb.maxs.x - origin.x) / cell).ceil() as usize + 1;
        let ny = ((aabb.maxs.y - origin.y) / cell).ceil() as usize + 1;
        let half_diagonal = cell * std::f32::consts::FRAC_1_SQRT_2;
        let lower = (0..nx * ny)
            .map(|k| {
                let c = origin
                    + Vector2::new(
                        ((k % nx) as f32 + 0.5) * cell,
                        ((k / nx) as f32 + 0.5) * cell,
                    );
                polyline.distance_to_local_point(&c, false) - half_diagonal
            })
            .collect();
        Self {
            origin,
            cell,
            nx,
            ny,
            lower,
        }
    }

    /// A lower bound of the distance from `p` to the walls (0 outside the grid).
    #[inline]
    fn at(&self, p: &Point2<f32>) -> f32 {
        let (fx, fy) = (
            (p.x - self.origin.x) / self.cell,
            (p.y - self.origin.y) / self.cell,
        );
        if fx < 0.0 || fy < 0.0 || fx as usize >= self.nx || fy as usize >= self.ny {
            return 0.0;
        }
        self.lower[fy as usize * self.nx + fx as usize]
    }
}

impl std::fmt::Debug for Walls {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Walls")
            .field("loops", &self.loops.len())
            .field("segments", &self.segment_count())
            .finish()
    }
}

impl Walls {
    /// Walls from closed loops (the first point is not repeated at the end); loops of fewer than
    /// two points are ignored.
    pub fn from_loops(loops: Vec<Vec<Point2<f64>>>) -> Self {
        let loops: Vec<_> = loops.into_iter().filter(|l| l.len() >= 2).collect();
        let mut vertices = Vec::new();
        let mut indices = Vec::new();
        for l in &loops {
            let base = vertices.len() as u32;
            let n = l.len() as u32;
            vertices.extend(l.iter().map(|p| Point2::new(p.x as f32, p.y as f32)));
            indices.extend((0..n).map(|i| [base + i, base + (i + 1) % n]));
        }
        let polyline = Polyline::new(vertices, Some(indices));
        Self {
            clearance: ClearanceGrid::new(&polyline),
            polyline,
            loops,
        }
    }

    /// Walls traced from a map image.
    pub fn from_map(map: &OccupancyMap) -> Self {
        let tolerance = 0.5 * map.resolution;
        let loops = trace_boundaries(map)
            .into_iter()
            .map(|l| {
                let pts: Vec<_> = l
                    .into_iter()
                    .map(|(hx, hy)| map.half_pixel_to_world(hx, hy))
                    .collect();
                simplify_closed(&pts, tolerance)
            })
            .collect();
        Self::from_loops(loops)
    }

    /// The closed wall loops, for drawing.
    pub fn loops(&self) -> &[Vec<Point2<f64>>] {
        &self.loops
    }

    /// Number of wall segments.
    pub fn segment_count(&self) -> usize {
        self.polyline.num_segments()
    }

    /// Distance from `origin` along the unit vector `dir` to the first wall, if within `max`.
    #[inline]
    pub fn cast_ray(&self, origin: Point2<f32>, dir: Vector2<f32>, max: f32) -> Option<f32> {
        self.polyline
            .cast_local_ray(&Ray::new(origin, dir), max, true)
    }

    /// Whether the straight path from `a` to `b` touches or crosses a wall.
    pub fn crosses_path(&self, a: Point2<f32>, b: Point2<f32>) -> bool {
        let d = b - a;
        let len = d.norm();
        if self.clearance.at(&a) > len {
            return false;
        }
        if len <= f32::EPSILON {
            return self.distance(&Point2::new(a.x as f64, a.y as f64)) <= 0.0;
        }
        self.cast_ray(a, d / len, len).is_some()
    }

    /// Whether a rectangle of half extents `half` at `pose` touches or crosses any wall.
    pub fn touches_box(&self, pose: &Isometry2<f32>, half: Vector2<f32>) -> bool {
        let centre = Point2::from(pose.translation.vector);
        if self.clearance.at(&centre) > half.norm() {
            return false;
        }
        let cuboid = Cuboid::new(half);
        let aabb = parry2d::shape::Shape::compute_aabb(&cuboid, pose);
        let to_box = pose.inverse();
        let touches = self.polyline.bvh().intersect_aabb(&aabb).any(|i| {
            let seg = self.polyline.segment(i);
            intersection_test_cuboid_segment(&to_box, &cuboid, &seg)
        });
        touches
    }

    /// The wall segments whose bounding boxes meet `aabb` (found through the BVH).
    pub fn segments_in<'a>(
        &'a self,
        aabb: &'a parry2d::bounding_volume::Aabb,
    ) -> impl Iterator<Item = parry2d::shape::Segment> + 'a {
        self.polyline
            .bvh()
            .intersect_aabb(aabb)
            .map(|i| self.polyline.segment(i))
    }

    /// Distance from `p` to the nearest wall.
    pub fn distance(&self, p: &Point2<f64>) -> f64 {
        use parry2d::query::PointQuery;
        let q = Point2::new(p.x as f32, p.y as f32);
        self.polyline.distance_to_local_point(&q, false) as f64
    }
}

/// Marching squares over the pixel centres, with everything outside the image occupied. Returns
/// closed loops of boundary vertices in half-pixel units (see [`OccupancyMap::half_pixel_to_world`]).
fn trace_boundaries(map: &OccupancyMap) -> Vec<Vec<(i64, i64)>> {
    let free = |c: i64, r: i64| !map.is_occupied(c as isize, r as isize);
    // edge midpoints of the cell whose bottom-left sample is (c, r)
    let bottom = |c: i64, r: i64| (2 * c + 1, 2 * r);
    let right = |c: i64, r: i64| (2 * c + 2, 2 * r + 1);
    let top = |c: i64, r: i64| (2 * c + 1, 2 * r + 2);
    let left = |c: i64, r: i64| (2 * c, 2 * r + 1);
    type Key = (i64, i64);
    let mut segments: Vec<(Key, Key)> = Vec::new();
    for r in -1..map.height as i64 {
        for c in -1..map.width as i64 {
            let case = (free(c, r) as u8)
                | (free(c + 1, r) as u8) << 1
                | (free(c + 1, r + 1) as u8) << 2
                | (free(c, r + 1) as u8) << 3;
            let (b, rt, t, l) = (bottom(c, r), right(c, r), top(c, r), left(c, r));
            let pairs: &[(Key, Key)] = match case {
                1 | 14 => &[(l, b)],
                2 | 13 => &[(b, rt)],
                3 | 12 => &[(l, rt)],
                4 | 11 => &[(rt, t)],
                6 | 9 => &[(b, t)],
                7 | 8 => &[(l, t)],
                // saddles: keep the two free corners apart (diagonal free pixels do not connect)
                5 => &[(l, b), (rt, t)],
                10 => &[(b, rt), (t, l)],
                _ => &[],
            };
            segments.extend_from_slice(pairs);
        }
    }
    // every boundary vertex has exactly two segments: walk the loops
    let mut at: HashMap<Key, [usize; 2]> = HashMap::with_capacity(segments.len() * 2);
    for (i, (a, b)) in segments.iter().enumerate() {
        for k in [a, b] {
            at.entry(*k)
                .and_modify(|e| e[1] = i)
                .or_insert([i, usize::MAX]);
        }
    }
    let mut used = vec![false; segments.len()];
    let mut loops = Vec::new();
    for start in 0..segments.len() {
        if used[start] {
            continue;
        }
        let mut lp = vec![segments[start].0];
        let mut current = start;
        let mut tip = segments[start].1;
        used[start] = true;
        loop {
            if tip == lp[0] {
                break;
            }
            lp.push(tip);
            let [s0, s1] = at[&tip];
            let next = if s0 == current { s1 } else { s0 };
            if next == usize::MAX || used[next] {
                break;
            }
            used[next] = true;
            let (a, b) = segments[next];
            tip = if a == tip { b } else { a };
            current = next;
        }
        loops.push(lp);
    }
    loops
}

/// Douglas–Peucker simplification of a closed loop: keeps every point farther than `tol` from the
/// simplified line.
pub fn simplify_closed(pts: &[Point2<f64>], tol: f64) -> Vec<Point2<f64>> {
    if pts.len() < 4 {
        return pts.to_vec();
    }
    let far = (1..pts.len())
        .max_by(|&a, &b| {
            (pts[a] - pts[0])
                .norm_squared()
                .total_cmp(&(pts[b] - pts[0]).norm_squared())
        })
        .unwrap_or(pts.len() / 2);
    let mut keep = vec![false; pts.len() + 1];
    keep[0] = true;
    keep[far] = true;
    let closed: Vec<_> = pts
        .iter()
        .chain(std::iter::once(&pts[0]))
        .copied()
        .collect();
    let mut stack = vec![(0usize, far), (far, pts.len())];
    while let Some((a, b)) = stack.pop() {
        if b <= a + 1 {
            continue;
        }
        let (pa, pb) = (closed[a], closed[b]);
        let d = pb - pa;
        let len = d.norm();
        let (mut worst, mut worst_i) = (0.0, a);
        for (i, p) in closed.iter().enumerate().take(b).skip(a + 1) {
            let dist = if len > 0.0 {
                (d.x * (p.y - pa.y) - d.y * (p.x - pa.x)).abs() / len
            } else {
                (p - pa).norm()
            };
            if dist > worst {
                worst = dist;
                worst_i = i;
            }
        }
        if worst > tol {
            keep[worst_i] = true;
            stack.push((a, worst_i));
            stack.push((worst_i, b));
        }
    }
    pts.iter()
        .zip(&keep)
        .filter_map(|(p, k)| k.then_some(*p))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn square_walls(half: f64) -> Walls {
        Walls::from_loops(vec![vec![
            Point2::new(-half, -half),
            Point2::new(half, -half),
            Point2::new(half, half),
            Point2::new(-half, half),
        ]])
    }

    #[test]
    fn rays_hit_the_square_at_the_analytic_distance() {
        let w = square_walls(2.0);
        let o = Point2::new(0.5f32, 0.0);
        assert!((w.cast_ray(o, Vector2::new(1.0, 0.0), 10.0).unwrap() - 1.5).abs() < 1e-6);
        let d = Vector2::new(1.0f32, 1.0).normalize();
        // hits x = 2 at t = 1.5·√2 before y = 2 at 2·√2
        let t = w.cast_ray(o, d, 10.0).unwrap();
        assert!((t - 1.5 * 2f32.sqrt()).abs() < 1e-5, "{t}");
        assert_eq!(w.cast_ray(o, Vector2::new(-1.0, 0.0), 2.0), None);
    }

    #[test]
    fn footprint_touching_and_clear() {
        let w = square_walls(2.0);
        let half = Vector2::new(0.29f32, 0.155);
        let at = |x: f32, y: f32, yaw: f32| Isometry2::new(Vector2::new(x, y), yaw);
        assert!(!w.touches_box(&at(0.0, 0.0, 0.3), half));
        assert!(!w.touches_box(&at(1.70, 0.0, 0.0), half)); // front at 1.99
        assert!(w.touches_box(&at(1.72, 0.0, 0.0), half)); // front at 2.01
                                                           // rotated 90°: the long side now points along y
        assert!(!w.touches_box(&at(0.0, 1.70, std::f32::consts::FRAC_PI_2), half));
        assert!(w.touches_box(&at(1.86, 0.0, std::f32::consts::FRAC_PI_2), half));
    }

    #[test]
    fn simplification_keeps_corners_and_drops_collinear_points() {
        let mut pts = Vec::new();
        for i in 0..10 {
            pts.push(Point2::new(i as f64, 0.0));
        }
        for i in 0..10 {
            pts.push(Point2::new(10.0, i as f64));
        }
        for i in 0..10 {
            pts.push(Point2::new(10.0 - i as f64, 10.0));
        }
        for i in 0..10 {
            pts.push(Point2::new(0.0, 10.0 - i as f64));
        }
        let s = simplify_closed(&pts, 0.01);
        assert_eq!(s.len(), 4, "{s:?}");
    }
}
