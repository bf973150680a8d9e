//! Constraints: a frustum, a polarity, a set of objects and an optional time window (§4.4.1).

use serde::{Deserialize, Serialize};

use super::frustum::{Frustum, RegionCache};
use super::path::PathTree;
use super::{BrowseError, finite};

/// Identifies a constraint within a browsing session (assigned by whoever creates it, e.g. the
/// query coordinator).
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
#[serde(transparent)]
pub struct ConstraintId(pub u64);

impl std::fmt::Display for ConstraintId {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}", self.0)
    }
}

/// §4.4.1: positive queries keep worlds whose motion passes through the volume, negative ones
/// keep worlds whose motion never does.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Polarity {
    /// "Passes through": some chosen object enters the frustum.
    Positive,
    /// "Never passes through": no chosen object enters the frustum.
    Negative,
}

/// A closed interval of simulated time, seconds. §4.4.1 ignores time by default (a query is
/// satisfied at any point of the motion); a window restricts it, like painting a region on the
/// time slider.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(try_from = "RawWindow")]
pub struct TimeWindow {
    start: f64,
    end: f64,
}

#[derive(Deserialize)]
struct RawWindow {
    start: f64,
    end: f64,
}

impl TryFrom<RawWindow> for TimeWindow {
    type Error = BrowseError;
    fn try_from(raw: RawWindow) -> Result<Self, BrowseError> {
        TimeWindow::new(raw.start, raw.end)
    }
}

impl TimeWindow {
    pub fn new(start: f64, end: f64) -> Result<Self, BrowseError> {
        let start = finite("window.start", start)?;
        let end = finite("window.end", end)?;
        if start > end {
            return Err(BrowseError::InvertedWindow { start, end });
        }
        Ok(Self { start, end })
    }

    pub fn start(&self) -> f64 {
        self.start
    }

    pub fn end(&self) -> f64 {
        self.end
    }

    pub fn contains(&self, t: f64) -> bool {
        self.start <= t && t <= self.end
    }
}

/// How the chosen objects combine (§4.4.1 asks that "one of these objects" pass through).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Quantifier {
    /// The question is whether *some* chosen object enters the volume (the default, §4.4.1).
    #[default]
    Any,
    /// The question is whether *every* chosen object enters the volume.
    All,
}

impl Quantifier {
    fn is_any(&self) -> bool {
        *self == Quantifier::Any
    }
}

/// Which part of each chosen object's motion the volume is tested against.
///
/// A world ends when its bodies come to rest or its end time is reached; from then on every
/// body stays at its final pose, for ever. So a time window that reaches past a world's end sees
/// the bodies where they ended ("ends in this bin" is asked as a window over the last seconds,
/// or with [`Scope::FinalPose`]).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Scope {
    /// The motion, in the time window if there is one, with the final pose held after the end.
    #[default]
    Motion,
    /// Only the final (resting) pose counts; takes no time window.
    FinalPose,
}

impl Scope {
    fn is_motion(&self) -> bool {
        *self == Scope::Motion
    }
}

/// A spatial query over the centre-of-mass paths of a subset of objects (§4.4.1). It travels as
/// JSON between the viewer, node-query and the stores; the frustum is validated on the way in,
/// the rest with [`validate`](Self::validate).
///
/// The question it asks of a world: does any (or, with [`Quantifier::All`], every) chosen object
/// enter the frustum — during the window, or in its final pose with [`Scope::FinalPose`]?
/// [`Polarity::Positive`] keeps the worlds where the answer is yes, [`Polarity::Negative`] those
/// where it is no: a negative constraint with `Any` keeps worlds where no chosen object enters,
/// with `All` worlds where at least one stays out.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Constraint {
    pub id: ConstraintId,
    pub polarity: Polarity,
    pub frustum: Frustum,
    /// Object indices (the scene's body order). An empty subset touches nothing: a positive
    /// constraint then keeps no world, a negative one all. An object a world does not have does
    /// not enter (so with `All` such a world fails a positive constraint).
    pub objects: Vec<u32>,
    #[serde(default, skip_serializing_if = "Quantifier::is_any")]
    pub quantifier: Quantifier,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub window: Option<TimeWindow>,
    #[serde(default, skip_serializing_if = "Scope::is_motion")]
    pub scope: Scope,
}

impl Constraint {
    /// What the types cannot say: a final-pose constraint takes no time window. The error
    /// names the field.
    pub fn validate(&self) -> Result<(), BrowseError> {
        if self.scope == Scope::FinalPose && self.window.is_some() {
            return Err(BrowseError::Conflict {
                field: "window",
                with: "scope = final_pose (only the final pose counts; it has no time window)",
            });
        }
        Ok(())
    }

    /// Whether the chosen objects' paths come within the frustum (inflated per object by the
    /// radius `path_of` returns with the tree: codec e_max + low-res deviation) — some of them,
    /// or every one with [`Quantifier::All`]. Objects the world does not have (`None`) do not
    /// touch it.
    pub fn touched<'a>(&self, path_of: impl FnMut(u32) -> Option<(&'a PathTree, f64)>) -> bool {
        self.touched_cached(&mut RegionCache::new(&self.frustum), path_of)
    }

    /// [`touched`](Self::touched) with the inflated frusta kept in `regions` (which must be a
    /// cache of this constraint's frustum), for evaluating many worlds.
    pub fn touched_cached<'a>(
        &self,
        regions: &mut RegionCache<'_>,
        mut path_of: impl FnMut(u32) -> Option<(&'a PathTree, f64)>,
    ) -> bool {
        debug_assert!(
            std::ptr::eq(regions.base(), &self.frustum) || *regions.base() == self.frustum
        );
        let mut enters = |object: u32| {
            path_of(object).is_some_and(|(tree, radius)| match self.scope {
                Scope::Motion => tree.intersects_cached(regions, self.window, radius),
                Scope::FinalPose => tree.final_pose_inside(regions.region(radius)),
            })
        };
        match self.quantifier {
            Quantifier::Any => self.objects.iter().any(|&o| enters(o)),
            Quantifier::All => !self.objects.is_empty() && self.objects.iter().all(|&o| enters(o)),
        }
    }

    /// Whether a world satisfies the constraint. Inflation makes positive answers a superset
    /// (no world that truly passes through is lost) and negative answers a subset (no world that
    /// truly passes through is kept): either way the error is on the side of the user's intent.
    pub fn evaluate<'a>(&self, path_of: impl FnMut(u32) -> Option<(&'a PathTree, f64)>) -> bool {
        self.satisfied_given(self.touched(path_of))
    }

    /// The answer for a world whose chosen objects do (`touched`) or do not enter the frustum.
    pub fn satisfied_given(&self, touched: bool) -> bool {
        match self.polarity {
            Polarity::Positive => touched,
            Polarity::Negative => !touched,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::browse::{Camera, Intrinsics, Polyline, ScreenRect, Viewport};

    fn constraint(polarity: Polarity, window: Option<TimeWindow>) -> Constraint {
        let camera = Camera {
            position: [0.0, 0.0, 10.0],
            rotation: [0.0, 0.0, 0.0, 1.0],
            intrinsics: Intrinsics::VerticalFov { fov_y_rad: 1.0 },
            viewport: Viewport {
                width: 640,
                height: 480,
            },
            near: 0.1,
            far: 100.0,
        };
        let rect = ScreenRect {
            x0: 310.0,
            y0: 230.0,
            x1: 330.0,
            y1: 250.0,
        };
        Constraint {
            id: ConstraintId(7),
            polarity,
            frustum: camera.frustum(&rect).expect("valid"),
            objects: vec![0, 2],
            quantifier: Quantifier::Any,
            window,
            scope: Scope::Motion,
        }
    }

    fn tree(y: f64) -> PathTree {
        // Crosses x = 0 at t = 1.
        PathTree::build(
            Polyline::new(vec![0.0, 2.0], vec![[-3.0, y, 0.0], [3.0, y, 0.0]]).expect("valid"),
        )
    }

    #[test]
    fn any_of_the_objects_polarity_and_window() {
        let hit = tree(0.0);
        let miss = tree(4.0);
        let paths = [&miss, &miss, &hit];
        let lookup = |o: u32| paths.get(o as usize).map(|t| (*t, 0.0));
        let pos = constraint(Polarity::Positive, None);
        let neg = constraint(Polarity::Negative, None);
        assert!(pos.evaluate(lookup));
        assert!(!neg.evaluate(lookup));
        // Object 2 is not in a two-object world; object 0 misses.
        let short = |o: u32| paths[..2].get(o as usize).map(|t| (*t, 0.0));
        assert!(!pos.evaluate(short));
        assert!(neg.evaluate(short));
        // Object 1 hits but is not chosen.
        let only1 = |o: u32| Some((if o == 1 { &hit } else { &miss }, 0.0));
        assert!(!pos.evaluate(only1));
        // The hit happens around t = 1: a window before it excludes it.
        let early = constraint(Polarity::Positive, TimeWindow::new(0.0, 0.5).ok());
        assert!(!early.evaluate(lookup));
        let around = constraint(Polarity::Positive, TimeWindow::new(0.9, 1.1).ok());
        assert!(around.evaluate(lookup));
        // Inflation: the miss at y = 4 is caught with a 5 m radius.
        assert!(pos.evaluate(|o| paths.get(o as usize).map(|_| (&miss, 5.0))));
    }

    /// Issue 24: `All` needs every chosen object in the volume; a window after a world's end
    /// sees its bodies at their final poses; a final-pose constraint tests only those.
    #[test]
    fn every_object_rest_poses_and_final_pose() {
        // Object 0 crosses the box at t = 1 and ends 3 m beside it at t = 2; object 2 slides
        // into the middle of the box and stays there from t = 2.
        let crosses = tree(0.0);
        let rests_inside = PathTree::build(
            Polyline::new(vec![0.0, 2.0], vec![[-3.0, 0.0, 0.0], [0.0, 0.0, 0.0]]).expect("valid"),
        );
        let miss = tree(4.0);
        let paths = [&crosses, &miss, &rests_inside];
        let lookup = |o: u32| paths.get(o as usize).map(|t| (*t, 0.0));
        let with = |quantifier, window: Option<TimeWindow>, scope| Constraint {
            quantifier,
            window,
            scope,
            ..constraint(Polarity::Positive, None)
        };
        let any = Quantifier::Any;
        let all = Quantifier::All;
        let motion = Scope::Motion;
        let fin = Scope::FinalPose;
        assert!(
            with(all, None, motion).evaluate(lookup),
            "both enter at some time"
        );
        // Long after both worlds' ends: only the body resting inside is there.
        let late = TimeWindow::new(5.0, 8.0).ok();
        assert!(with(any, late, motion).evaluate(lookup));
        assert!(!with(all, late, motion).evaluate(lookup));
        assert!(with(any, None, fin).evaluate(lookup));
        assert!(!with(all, None, fin).evaluate(lookup));
        // Negative + all: keeps worlds where at least one chosen object stays out.
        let neg_all = Constraint {
            polarity: Polarity::Negative,
            ..with(all, late, motion)
        };
        assert!(neg_all.evaluate(lookup));
        // A world without object 2 fails "all" (the missing object never enters).
        let short = |o: u32| paths[..2].get(o as usize).map(|t| (*t, 0.0));
        assert!(!with(all, None, motion).evaluate(short));
        // No objects: "all" is not vacuously true.
        let none = Constraint {
            objects: vec![],
            ..with(all, None, motion)
        };
        assert!(!none.evaluate(lookup));
        // Final pose and window do not mix.
        let bad = with(any, late, fin);
        assert_eq!(
            bad.validate(),
            Err(BrowseError::Conflict {
                field: "window",
                with: "scope = final_pose (only the final pose counts; it has no time window)"
            })
        );
        assert_eq!(with(all, late, motion).validate(), Ok(()));
        // Defaults stay off the wire; set values travel.
        let text = serde_json::to_string(&with(any, None, motion)).expect("serialises");
        assert!(
            !text.contains("quantifier") && !text.contains("scope"),
            "{text}"
        );
        let text = serde_json::to_string(&with(all, None, fin)).expect("serialises");
        assert!(
            text.contains(r#""quantifier":"all""#) && text.contains(r#""scope":"final_pose""#),
            "{text}"
        );
        let back: Constraint = serde_json::from_str(&text).expect("parses");
        assert_eq!((back.quantifier, back.scope), (all, fin));
    }

    #[test]
    fn window_validation() {
        assert_eq!(
            TimeWindow::new(2.0, 1.0),
            Err(BrowseError::InvertedWindow {
                start: 2.0,
                end: 1.0
            })
        );
        assert!(matches!(
            TimeWindow::new(f64::NAN, 1.0),
            Err(BrowseError::NonFinite { .. })
        ));
    }

    #[test]
    fn serde_roundtrip_and_validation() {
        let c = constraint(Polarity::Negative, TimeWindow::new(0.5, 1.5).ok());
        let text = toml::to_string(&c).expect("serialises");
        let back: Constraint = toml::from_str(&text).expect("parses");
        assert_eq!(back.id, c.id);
        assert_eq!(back.polarity, c.polarity);
        assert_eq!(back.objects, c.objects);
        assert_eq!(back.window, c.window);
        for (a, b) in back.frustum.planes().iter().zip(c.frustum.planes()) {
            assert!((a.offset - b.offset).abs() < 1e-12);
        }
        assert!(text.contains("polarity = \"negative\""), "{text}");
        let inverted = text.replace("start = 0.5", "start = 5.0");
        assert_ne!(inverted, text);
        assert!(toml::from_str::<Constraint>(&inverted).is_err());
        let no_window = constraint(Polarity::Positive, None);
        let text = toml::to_string(&no_window).expect("serialises");
        let back: Constraint = toml::from_str(&text).expect("parses");
        assert_eq!(back.window, None);
    }
}
