//! Contact generation (the "collision detection code" §3.1 assumes) and the contact Jacobian
//! (3.3)–(3.12).
//!
//! Each pair of shapes whose bounding boxes come within the prediction distance keeps its parry
//! contact manifolds and workspace from step to step ([`NarrowPhase`]), so parry can track
//! contacts by their feature ids. A [`Contact`] is one point of one manifold, in world
//! coordinates, with a normal that pushes its first body (`body`) away from the other and two
//! tangents `u`, `w` spanning the (box-approximated) friction pyramid. Contacts form islands,
//! the connected components of the graph whose nodes are dynamic bodies and whose edges are
//! contacts and joints between two dynamic bodies; each island is its own LCP (static geometry
//! and the world end of a joint do not join islands).

use std::collections::BTreeMap;

use nalgebra::Vector3;
use parry3d::bounding_volume::BoundingVolume;
use parry3d::query::PersistentQueryDispatcher;
use parry3d::query::{ContactManifold, ContactManifoldsWorkspace, DefaultQueryDispatcher};

use crate::body::{Body, Material, StaticBody, from_vec3};
use crate::joint::JointRow;

/// Contact points of one pair closer than this (m) with the same normal are merged.
pub const DUPLICATE_DISTANCE: f64 = 1e-6;

/// The other side of a contact.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum Partner {
    /// A dynamic body (index into `World::bodies`).
    Body(usize),
    /// Static geometry (index into `World::statics`).
    Static(usize),
}

/// One contact point.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Contact {
    /// The dynamic body pushed along `+normal`.
    pub body: usize,
    /// The other side, pushed along `−normal` if dynamic.
    pub partner: Partner,
    /// World contact point (midpoint of parry's two witness points).
    pub point: Vector3<f64>,
    /// Unit normal, from the partner towards `body`.
    pub normal: Vector3<f64>,
    /// First friction direction; the stepper aligns it with the slip (§3.6.1).
    pub tangent_u: Vector3<f64>,
    /// Second friction direction, `normal × tangent_u`.
    pub tangent_w: Vector3<f64>,
    /// Signed distance (negative: penetration).
    pub dist: f64,
    /// Pair friction coefficient.
    pub friction: f64,
    /// Pair restitution coefficient.
    pub restitution: f64,
    /// parry feature ids of the two shapes (identify a contact between steps).
    pub features: (u32, u32),
    /// Rolling resistance arm (m) of the pair, the larger of the two bodies'
    /// [`Body::rolling_resistance`]; zero: the contact has no rolling rows (§5.3.5).
    pub rolling: f64,
    /// First rolling-friction axis, unit; the stepper aligns it with the relative angular
    /// velocity like `tangent_u` with the slip. See [`Contact::rolling_axes`].
    pub roll_axis: Vector3<f64>,
}

impl Contact {
    /// The faster of the two bodies' velocities at the contact point, `|v + ω × (p − x)|`
    /// (m/s; a static's is 0): how far into the contact that point can have moved in one step,
    /// per second, in a stepper without continuous collision detection.
    pub fn point_speed(&self, bodies: &[crate::Body]) -> f64 {
        let at = |b: usize| {
            bodies.get(b).map_or(0.0, |b| {
                (b.linvel + b.angvel.cross(&(self.point - b.position))).norm()
            })
        };
        let partner = match self.partner {
            Partner::Body(p) => at(p),
            Partner::Static(_) => 0.0,
        };
        at(self.body).max(partner)
    }

    /// Re-aligns the tangents so that `tangent_u` is along the tangential part of `direction`;
    /// when that part is (numerically) zero, keeps a deterministic basis. Returns whether the
    /// direction was used.
    pub fn align_tangents(&mut self, direction: &Vector3<f64>, min_norm: f64) -> bool {
        let tangential = direction - self.normal * self.normal.dot(direction);
        let norm = tangential.norm();
        if norm > min_norm && norm.is_finite() {
            self.tangent_u = tangential / norm;
            self.tangent_w = self.normal.cross(&self.tangent_u);
            true
        } else {
            let (u, w) = default_tangents(&self.normal);
            self.tangent_u = u;
            self.tangent_w = w;
            false
        }
    }
}

impl Contact {
    /// The three axes of the rolling-friction rows (5.15)–(5.17): `roll_axis` and a
    /// deterministic orthonormal completion.
    pub fn rolling_axes(&self) -> [Vector3<f64>; 3] {
        let (a, b) = default_tangents(&self.roll_axis);
        [self.roll_axis, a, b]
    }

    /// Aligns `roll_axis` with `omega` (the relative angular velocity) when it is longer than
    /// `min_norm`, else resets it to the normal. Returns whether `omega` was used.
    pub fn align_rolling(&mut self, omega: &Vector3<f64>, min_norm: f64) -> bool {
        let norm = omega.norm();
        if norm > min_norm && norm.is_finite() {
            self.roll_axis = omega / norm;
            true
        } else {
            self.roll_axis = self.normal;
            false
        }
    }
}

/// A deterministic orthonormal tangent pair for a unit normal.
pub fn default_tangents(n: &Vector3<f64>) -> (Vector3<f64>, Vector3<f64>) {
    // Cross with the world axis least aligned with n.
    let axis = if n.x.abs() <= n.y.abs() && n.x.abs() <= n.z.abs() {
        Vector3::x()
    } else if n.y.abs() <= n.z.abs() {
        Vector3::y()
    } else {
        Vector3::z()
    };
    let u = n.cross(&axis).normalize();
    let w = n.cross(&u);
    (u, w)
}

/// An island: bodies coupled by contacts and joints, solved as one LCP.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct Island {
    /// Dynamic bodies, ascending.
    pub bodies: Vec<usize>,
    /// Indices into [`ContactSet::contacts`], ascending.
    pub contacts: Vec<usize>,
    /// Indices into [`ContactSet::joints`] (joint rows), ascending.
    pub joints: Vec<usize>,
}

/// The contacts and joint rows of one step and their islands. Carried by step reports so that
/// a step can be replayed with exactly the same contact set, Jacobian and joint goals
/// ([`crate::World::step_forward_with`]).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct ContactSet {
    /// All contacts.
    pub contacts: Vec<Contact>,
    /// All joint rows (§5.3.4), each an equality row of its island's LCP.
    pub joints: Vec<JointRow>,
    /// Connected components that have at least one contact or joint row.
    pub islands: Vec<Island>,
}

impl ContactSet {
    /// Builds the islands of `contacts` over `n_bodies` dynamic bodies (union–find).
    /// Contacts naming a body index out of range are dropped.
    pub fn new(contacts: Vec<Contact>, n_bodies: usize) -> Self {
        Self::with_joints(contacts, Vec::new(), n_bodies)
    }

    /// As [`ContactSet::new`], with joint rows: bodies joined by a joint share an island.
    /// Contacts and rows naming a body index out of range are dropped.
    pub fn with_joints(contacts: Vec<Contact>, joints: Vec<JointRow>, n_bodies: usize) -> Self {
        let contacts: Vec<Contact> = contacts
            .into_iter()
            .filter(|c| {
                c.body < n_bodies
                    && match c.partner {
                        Partner::Body(b) => b < n_bodies && b != c.body,
                        Partner::Static(_) => true,
                    }
            })
            .collect();
        let joints: Vec<JointRow> = joints
            .into_iter()
            .filter(|j| {
                j.row.a.0 < n_bodies && j.row.b.is_none_or(|(b, _)| b < n_bodies && b != j.row.a.0)
            })
            .collect();
        let mut parent: Vec<usize> = (0..n_bodies).collect();
        fn find(parent: &mut [usize], mut i: usize) -> usize {
            while parent[i] != i {
                parent[i] = parent[parent[i]];
                i = parent[i];
            }
            i
        }
        let edges = contacts
            .iter()
            .filter_map(|c| match c.partner {
                Partner::Body(b) => Some((c.body, b)),
                Partner::Static(_) => None,
            })
            .chain(
                joints
                    .iter()
                    .filter_map(|j| j.row.b.map(|(b, _)| (j.row.a.0, b))),
            );
        for (a, b) in edges {
            let (ra, rb) = (find(&mut parent, a), find(&mut parent, b));
            // Smallest index as root keeps island order deterministic.
            if ra < rb {
                parent[rb] = ra;
            } else if rb < ra {
                parent[ra] = rb;
            }
        }
        let mut by_root: BTreeMap<usize, Island> = BTreeMap::new();
        for (k, c) in contacts.iter().enumerate() {
            let root = find(&mut parent, c.body);
            by_root.entry(root).or_default().contacts.push(k);
        }
        for (k, j) in joints.iter().enumerate() {
            let root = find(&mut parent, j.row.a.0);
            by_root.entry(root).or_default().joints.push(k);
        }
        for b in 0..n_bodies {
            let root = find(&mut parent, b);
            if let Some(island) = by_root.get_mut(&root) {
                island.bodies.push(b);
            }
        }
        Self {
            contacts,
            joints,
            islands: by_root.into_values().collect(),
        }
    }

    /// Number of contacts.
    pub fn len(&self) -> usize {
        self.contacts.len()
    }

    /// True without contacts.
    pub fn is_empty(&self) -> bool {
        self.contacts.is_empty()
    }
}

/// One row of the contact Jacobian `J` (3.4), (3.12): the 6-vectors `(d, r × d)` for the
/// pushed body and `(−d, −r × d)` for a dynamic partner.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct JacobianRow {
    /// `(body, [linear; angular])` of the first body.
    pub a: (usize, [f64; 6]),
    /// Same for the partner, if dynamic.
    pub b: Option<(usize, [f64; 6])>,
}

impl JacobianRow {
    /// The row for direction `dir` at `contact`, with lever arms from the bodies' centres of
    /// mass.
    pub fn new(contact: &Contact, dir: &Vector3<f64>, bodies: &[Body]) -> Self {
        let half = |body: usize, sign: f64| {
            let r = contact.point - bodies[body].position;
            let ang = r.cross(dir);
            (
                body,
                [
                    sign * dir.x,
                    sign * dir.y,
                    sign * dir.z,
                    sign * ang.x,
                    sign * ang.y,
                    sign * ang.z,
                ],
            )
        };
        Self {
            a: half(contact.body, 1.0),
            b: match contact.partner {
                Partner::Body(b) => Some(half(b, -1.0)),
                Partner::Static(_) => None,
            },
        }
    }

    /// The row of a rolling-friction direction (5.15)–(5.17): relative angular velocity about
    /// `axis`, no linear part.
    pub fn angular(contact: &Contact, axis: &Vector3<f64>) -> Self {
        let half = |body: usize, sign: f64| {
            (
                body,
                [0.0, 0.0, 0.0, sign * axis.x, sign * axis.y, sign * axis.z],
            )
        };
        Self {
            a: half(contact.body, 1.0),
            b: match contact.partner {
                Partner::Body(b) => Some(half(b, -1.0)),
                Partner::Static(_) => None,
            },
        }
    }

    /// `J v`: relative velocity along the row's direction.
    pub fn velocity(&self, bodies: &[Body]) -> f64 {
        let dot = |(i, j): &(usize, [f64; 6])| {
            let b = &bodies[*i];
            j[0] * b.linvel.x
                + j[1] * b.linvel.y
                + j[2] * b.linvel.z
                + j[3] * b.angvel.x
                + j[4] * b.angvel.y
                + j[5] * b.angvel.z
        };
        dot(&self.a) + self.b.as_ref().map_or(0.0, dot)
    }
}

#[derive(Clone, Default)]
struct PairCache {
    manifolds: Vec<ContactManifold<(), ()>>,
    workspace: Option<ContactManifoldsWorkspace>,
}

/// Persistent narrow phase: parry manifolds and workspaces per shape pair, kept across steps.
#[derive(Clone, Default)]
pub struct NarrowPhase {
    pairs: BTreeMap<(usize, Partner), PairCache>,
}

impl std::fmt::Debug for NarrowPhase {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("NarrowPhase")
            .field("pairs", &self.pairs.len())
            .finish()
    }
}

impl NarrowPhase {
    /// Forgets every cached manifold.
    pub fn clear(&mut self) {
        self.pairs.clear();
    }

    /// All contact points with `dist ≤ prediction` at the bodies' current poses, tangents in
    /// the default basis. Pairs that parry cannot handle are skipped and counted in the second
    /// return value. Candidate pairs come from the sweep-and-prune broad phase
    /// ([`crate::broad_phase`]); bodies far from everything cost one bounding box each.
    pub fn detect(
        &mut self,
        bodies: &[Body],
        statics: &[StaticBody],
        prediction: f64,
    ) -> (Vec<Contact>, usize) {
        let pred = prediction.max(0.0) as f32;
        let body_aabbs: Vec<_> = bodies
            .iter()
            .map(|b| {
                b.enabled
                    .then(|| b.shape.compute_aabb(&b.pose()).loosened(pred))
            })
            .collect();
        let static_aabbs: Vec<_> = statics
            .iter()
            .map(|s| s.shape.compute_aabb(&s.pose()).loosened(pred))
            .collect();
        let live = crate::broad_phase::sweep_and_prune(&body_aabbs, &static_aabbs);
        let mut contacts = Vec::new();
        let mut unsupported = 0;
        for &key in &live {
            let bi = &bodies[key.0];
            let ok = match key.1 {
                Partner::Static(s) => {
                    let st = &statics[s];
                    let mat = bi.material.combine(st.material);
                    let rolling = bi.rolling_resistance;
                    self.pair(
                        key,
                        bi,
                        &st.shape,
                        st.pose(),
                        (mat, rolling),
                        pred,
                        &mut contacts,
                    )
                }
                Partner::Body(j) => {
                    let bj = &bodies[j];
                    let mat = bi.material.combine(bj.material);
                    let rolling = bi.rolling_resistance.max(bj.rolling_resistance);
                    self.pair(
                        key,
                        bi,
                        &bj.shape,
                        bj.pose(),
                        (mat, rolling),
                        pred,
                        &mut contacts,
                    )
                }
            };
            if !ok {
                unsupported += 1;
            }
        }
        // Drop caches of pairs that separated (`live` is sorted, but in its own order).
        let mut sorted = live;
        sorted.sort_unstable();
        self.pairs.retain(|k, _| sorted.binary_search(k).is_ok());
        (contacts, unsupported)
    }

    /// The contacts of the pairs `keys` at the given (predicted) poses, computed on copies of
    /// the cached manifolds so that the narrow phase itself is untouched: exactly what
    /// [`NarrowPhase::detect`] would return for those pairs if the bodies were where `body`
    /// puts them now. `body(i)` is body `i` at its predicted pose (`None`: skip the pairs that
    /// name it), so a caller predicting a few bodies of a large world copies only those. Used
    /// by the backward step to look one step ahead (see [`crate::backward`]). Pairs without a
    /// cache are computed from scratch.
    pub fn predict<'a>(
        &self,
        keys: &[(usize, Partner)],
        body: impl Fn(usize) -> Option<&'a Body>,
        statics: &[StaticBody],
        prediction: f64,
    ) -> Vec<Contact> {
        let pred = prediction.max(0.0) as f32;
        let mut out = Vec::new();
        for &key in keys {
            let Some(bi) = body(key.0) else {
                continue;
            };
            let mut cache = self.pairs.get(&key).cloned().unwrap_or_default();
            let (shape, pose, mat) = match key.1 {
                Partner::Static(s) => match statics.get(s) {
                    Some(st) => (
                        &st.shape,
                        st.pose(),
                        (bi.material.combine(st.material), bi.rolling_resistance),
                    ),
                    None => continue,
                },
                Partner::Body(j) => match body(j) {
                    Some(bj) => (
                        &bj.shape,
                        bj.pose(),
                        (
                            bi.material.combine(bj.material),
                            bi.rolling_resistance.max(bj.rolling_resistance),
                        ),
                    ),
                    None => continue,
                },
            };
            pair_contacts(key, bi, shape, pose, mat, pred, &mut cache, &mut out);
        }
        out
    }

    #[allow(clippy::too_many_arguments)]
    fn pair(
        &mut self,
        key: (usize, Partner),
        body: &Body,
        other_shape: &parry3d::shape::SharedShape,
        other_pose: parry3d::math::Pose,
        material: (Material, f64),
        prediction: f32,
        out: &mut Vec<Contact>,
    ) -> bool {
        let cache = self.pairs.entry(key).or_default();
        pair_contacts(
            key,
            body,
            other_shape,
            other_pose,
            material,
            prediction,
            cache,
            out,
        )
    }
}

/// One pair's contact points, updating its cached manifolds; false if parry cannot handle the
/// pair.
#[allow(clippy::too_many_arguments)]
fn pair_contacts(
    key: (usize, Partner),
    body: &Body,
    other_shape: &parry3d::shape::SharedShape,
    other_pose: parry3d::math::Pose,
    (material, rolling): (Material, f64),
    prediction: f32,
    cache: &mut PairCache,
    out: &mut Vec<Contact>,
) -> bool {
    let pose1 = body.pose();
    let pos12 = pose1.inverse() * other_pose;
    let ok = DefaultQueryDispatcher
        .contact_manifolds(
            &pos12,
            body.shape.as_ref(),
            other_shape.as_ref(),
            prediction,
            &mut cache.manifolds,
            &mut cache.workspace,
        )
        .is_ok();
    if !ok {
        return false;
    }
    let first = out.len();
    for m in &cache.manifolds {
        let sub1 = m.subshape_pos1().copied();
        let sub2 = m.subshape_pos2().copied();
        let n1_local = sub1.map_or(m.local_n1, |p| p.transform_vector(m.local_n1));
        let n1 = from_vec3(pose1.transform_vector(n1_local));
        let Some(n1) = n1.try_normalize(1e-6) else {
            continue;
        };
        for p in &m.points {
            if p.dist > prediction {
                continue;
            }
            let l1 = sub1.map_or(p.local_p1, |s| s.transform_point(p.local_p1));
            let l2 = sub2.map_or(p.local_p2, |s| s.transform_point(p.local_p2));
            let w1 = from_vec3(pose1.transform_point(l1));
            let w2 = from_vec3(other_pose.transform_point(l2));
            // parry's n1 points out of shape 1 towards shape 2; the impulse on body 1
            // pushes it the other way.
            let normal = -n1;
            let point = 0.5 * (w1 + w2);
            // Coincident faces can come back as two manifolds repeating the same corners;
            // a repeated row would only make the LCP degenerate.
            let duplicate = out[first..].iter().any(|c| {
                (c.point - point).norm() <= DUPLICATE_DISTANCE
                    && c.normal.dot(&normal) >= 1.0 - 1e-6
            });
            if duplicate {
                continue;
            }
            let (tangent_u, tangent_w) = default_tangents(&normal);
            out.push(Contact {
                body: key.0,
                partner: key.1,
                point,
                normal,
                tangent_u,
                tangent_w,
                dist: p.dist as f64,
                friction: material.friction,
                restitution: material.restitution,
                features: (p.fid1.0, p.fid2.0),
                rolling,
                roll_axis: normal,
            });
        }
    }
    true
}
