//! Exact collisions: car–car rectangle overlap and car–wall contact.
//!
//! Two cars collide when their rectangles overlap with positive depth: by the separating axis theorem
//! two rectangles are apart exactly when one of the four edge normals separates them, so touching
//! (separation 0) is not a collision. A car hits a wall when any wall segment touches or crosses its
//! rectangle ([`WallContact::Footprint`]), when its centre crosses a wall during the physics step
//! ([`WallContact::Centre`]), or, as in the paper's code, when its centre lies in an occupied
//! pixel of the map ([`WallContact::CentrePixel`]).

use crate::vehicle::{idx, State, VehicleParams};
use ctxrace_config::WallContact;
use ctxrace_tracks::{Track, Walls};
use nalgebra::{Isometry2, Point2, Vector2};
use parry2d::query::sat::cuboid_cuboid_find_local_separating_normal_oneway;
use parry2d::shape::Cuboid;

/// A car's rectangle in the world.
#[derive(Clone, Copy, Debug)]
pub struct CarBox {
    /// Pose of the rectangle's centre (the car's reference point).
    pub pose: Isometry2<f32>,
    /// The rectangle.
    pub shape: Cuboid,
}

impl CarBox {
    /// Upper bound on the distance from the centre to a corner of any car this crate simulates
    /// (half the diagonal of 0.58 × 0.31 m, rounded up).
    pub const CIRCUMRADIUS: f32 = 0.33;

    /// The rectangle of a car in state `x`.
    pub fn new(x: &State, p: &VehicleParams) -> Self {
        Self {
            pose: Isometry2::new(
                Vector2::new(x[idx::X] as f32, x[idx::Y] as f32),
                x[idx::YAW] as f32,
            ),
            shape: Cuboid::new(Vector2::new(p.length as f32 / 2.0, p.width as f32 / 2.0)),
        }
    }

    /// Centre point.
    pub fn centre(&self) -> Point2<f32> {
        Point2::from(self.pose.translation.vector)
    }

    /// The four corners in the world, counter-clockwise.
    pub fn corners(&self) -> [Point2<f32>; 4] {
        let h = self.shape.half_extents;
        [(h.x, h.y), (-h.x, h.y), (-h.x, -h.y), (h.x, -h.y)]
            .map(|(x, y)| self.pose * Point2::new(x, y))
    }

    /// Whether the two rectangles overlap with positive depth (touching is not a collision).
    pub fn overlaps(&self, other: &CarBox) -> bool {
        let reach = self.shape.half_extents.norm() + other.shape.half_extents.norm();
        if (self.centre() - other.centre()).norm() >= reach {
            return false;
        }
        let pos12 = self.pose.inv_mul(&other.pose);
        let sep1 =
            cuboid_cuboid_find_local_separating_normal_oneway(&self.shape, &other.shape, &pos12).0;
        if sep1 >= 0.0 {
            return false;
        }
        let pos21 = pos12.inverse();
        cuboid_cuboid_find_local_separating_normal_oneway(&other.shape, &self.shape, &pos21).0 < 0.0
    }

    /// Whether the rectangle touches or crosses a wall.
    pub fn hits_wall(&self, walls: &Walls) -> bool {
        walls.touches_box(&self.pose, self.shape.half_extents)
    }

    /// Whether a car that was centred at `from` one physics step ago and is now this rectangle,
    /// centred at `now` (its state's position, unrounded), hit a wall of `track` under `rule`.
    pub fn hits_wall_by(
        &self,
        rule: WallContact,
        from: Point2<f32>,
        now: &Point2<f64>,
        track: &Track,
    ) -> bool {
        match (rule, &track.map) {
            (WallContact::Footprint, _) => self.hits_wall(&track.walls),
            (WallContact::CentrePixel, Some(map)) => map.occupied_at(now),
            (WallContact::Centre | WallContact::CentrePixel, _) => {
                track.walls.crosses_path(from, self.centre())
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn car(x: f64, y: f64, yaw: f64) -> CarBox {
        let mut s = [0.0; 7];
        s[idx::X] = x;
        s[idx::Y] = y;
        s[idx::YAW] = yaw;
        CarBox::new(&s, &VehicleParams::default())
    }

    #[test]
    fn nose_to_tail_overlap_and_clearance() {
        let a = car(0.0, 0.0, 0.0);
        assert!(a.overlaps(&car(0.57, 0.0, 0.0)));
        assert!(!a.overlaps(&car(0.59, 0.0, 0.0)));
        // side by side: widths 0.31
        assert!(a.overlaps(&car(0.0, 0.30, 0.0)));
        assert!(!a.overlaps(&car(0.0, 0.32, 0.0)));
        // crossing at right angles: half length + half width = 0.445
        assert!(a.overlaps(&car(0.44, 0.0, std::f64::consts::FRAC_PI_2)));
        assert!(!a.overlaps(&car(0.45, 0.0, std::f64::consts::FRAC_PI_2)));
        // rotated 45°: corner reach √(0.29² + 0.155²)-ish region; symmetric answers
        let b = car(0.5, 0.2, 0.785);
        assert_eq!(a.overlaps(&b), b.overlaps(&a));
    }
}
