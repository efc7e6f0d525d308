#![forbid(unsafe_code)]
//! A bounding volume hierarchy over primitive bounds: binned surface-area-heuristic build, closest-hit
//! traversal that visits the nearer child first and prunes boxes beyond the best hit so far.

use nalgebra::{Point3, Vector3};

/// Leaves hold at most this many primitives unless their centroids cannot be split.
const MAX_LEAF: usize = 4;
/// SAH candidate split planes per axis.
const BINS: usize = 16;
/// Relative cost of visiting a node versus intersecting one primitive.
const TRAVERSAL_COST: f64 = 1.0;

/// An axis-aligned box.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Aabb {
    pub min: Point3<f64>,
    pub max: Point3<f64>,
}

impl Aabb {
    pub fn empty() -> Self {
        Self {
            min: Point3::from([f64::INFINITY; 3]),
            max: Point3::from([f64::NEG_INFINITY; 3]),
        }
    }

    pub fn grow_point(&mut self, p: &Point3<f64>) {
        self.min = self.min.inf(p);
        self.max = self.max.sup(p);
    }

    pub fn grow(&mut self, other: &Aabb) {
        self.min = self.min.inf(&other.min);
        self.max = self.max.sup(&other.max);
    }

    fn centroid(&self) -> Point3<f64> {
        nalgebra::center(&self.min, &self.max)
    }

    fn half_area(&self) -> f64 {
        let e = self.max - self.min;
        if e.iter().any(|v| *v < 0.0) {
            return 0.0;
        }
        e.x * e.y + e.y * e.z + e.z * e.x
    }

    /// Entry distance of the ray into the box if it enters before `t_max` (0 when starting inside).
    #[inline]
    fn entry(
        &self,
        origin: &Point3<f64>,
        inverse_direction: &Vector3<f64>,
        t_max: f64,
    ) -> Option<f64> {
        let mut t_near = 0.0_f64;
        let mut t_far = t_max;
        for i in 0..3 {
            let t1 = (self.min[i] - origin[i]) * inverse_direction[i];
            let t2 = (self.max[i] - origin[i]) * inverse_direction[i];
            // `max`/`min` skip a NaN (a zero direction component with the origin on the slab plane).
            t_near = t_near.max(t1.min(t2));
            t_far = t_far.min(t1.max(t2));
        }
        (t_near <= t_far).then_some(t_near)
    }
}

#[derive(Debug, Clone)]
struct Node {
    bounds: Aabb,
    /// Leaf: first index into `Bvh::order`; interior: index of the left child (the right is next).
    first: u32,
    /// Leaf: number of primitives (> 0); interior: 0.
    count: u32,
}

/// The hierarchy: nodes (root first) and the primitive order its leaves refer to.
#[derive(Debug, Clone)]
pub(crate) struct Bvh {
    nodes: Vec<Node>,
    order: Vec<u32>,
}

impl Bvh {
    /// Primitive index of each leaf slot: callers store primitives in this order so leaves are contiguous.
    pub fn order(&self) -> &[u32] {
        &self.order
    }

    /// Builds over the bounds of each primitive (index = primitive index).
    pub fn build(bounds: &[Aabb]) -> Self {
        let mut order: Vec<u32> = (0..bounds.len() as u32).collect();
        let centroids: Vec<Point3<f64>> = bounds.iter().map(Aabb::centroid).collect();
        let mut nodes = vec![Node {
            bounds: Aabb::empty(),
            first: 0,
            count: bounds.len() as u32,
        }];
        if bounds.is_empty() {
            return Self { nodes, order };
        }
        // Explicit work list (node index, start, end): no recursion depth limit on skewed scenes.
        let mut work = vec![(0usize, 0usize, bounds.len())];
        while let Some((node, start, end)) = work.pop() {
            let mut node_bounds = Aabb::empty();
            let mut centroid_bounds = Aabb::empty();
            for &i in &order[start..end] {
                node_bounds.grow(&bounds[i as usize]);
                centroid_bounds.grow_point(&centroids[i as usize]);
            }
            nodes[node].bounds = node_bounds;
            nodes[node].first = start as u32;
            nodes[node].count = (end - start) as u32;
            if end - start <= MAX_LEAF {
                continue;
            }
            let Some(mid) = split(
                &mut order[start..end],
                bounds,
                &centroids,
                &node_bounds,
                &centroid_bounds,
            ) else {
                continue;
            };
            let left = nodes.len();
            nodes.push(Node {
                bounds: Aabb::empty(),
                first: 0,
                count: 0,
            });
            nodes.push(Node {
                bounds: Aabb::empty(),
                first: 0,
                count: 0,
            });
            nodes[node].first = left as u32;
            nodes[node].count = 0;
            work.push((left, start, start + mid));
            work.push((left + 1, start + mid, end));
        }
        Self { nodes, order }
    }

    /// Closest hit within `(0, max_range]`: `intersect(slot, t_max)` gives the hit distance of the primitive
    /// in leaf slot `slot` (see [`Bvh::order`]) if it is at most `t_max`. Returns `(distance, slot)`.
    pub fn closest(
        &self,
        stack: &mut Vec<(u32, f64)>,
        origin: &Point3<f64>,
        direction: &Vector3<f64>,
        max_range: f64,
        intersect: impl Fn(usize, f64) -> Option<f64>,
    ) -> Option<(f64, usize)> {
        let inverse = direction.map(|v| 1.0 / v);
        let mut best_t = max_range;
        let mut best = None;
        let root = &self.nodes[0];
        if self.order.is_empty() {
            return None;
        }
        let root_entry = root.bounds.entry(origin, &inverse, best_t)?;
        stack.clear();
        stack.push((0, root_entry));
        while let Some((index, entry)) = stack.pop() {
            if entry > best_t {
                continue;
            }
            let node = &self.nodes[index as usize];
            if node.count > 0 {
                let first = node.first as usize;
                for slot in first..first + node.count as usize {
                    if let Some(t) = intersect(slot, best_t) {
                        best_t = t;
                        best = Some(slot);
                    }
                }
                continue;
            }
            let (left, right) = (node.first, node.first + 1);
            let left_entry = self.nodes[left as usize]
                .bounds
                .entry(origin, &inverse, best_t);
            let right_entry = self.nodes[right as usize]
                .bounds
                .entry(origin, &inverse, best_t);
            match (left_entry, right_entry) {
                (Some(l), Some(r)) => {
                    // Far child first onto the stack so the near one is popped next.
                    if l <= r {
                        stack.push((right, r));
                        stack.push((left, l));
                    } else {
                        stack.push((left, l));
                        stack.push((right, r));
                    }
                }
                (Some(l), None) => stack.push((left, l)),
                (None, Some(r)) => stack.push((right, r)),
                (None, None) => {}
            }
        }
        best.map(|primitive| (best_t, primitive))
    }
}

/// Reorders `order` so `[..mid]` and `[mid..]` are the two children; `None` keeps the range as a leaf.
fn split(
    order: &mut [u32],
    bounds: &[Aabb],
    centroids: &[Point3<f64>],
    node_bounds: &Aabb,
    centroid_bounds: &Aabb,
) -> Option<usize> {
    let count = order.len();
    let extent = centroid_bounds.max - centroid_bounds.min;
    let leaf_cost = count as f64;
    let mut best: Option<(f64, usize, usize)> = None; // (cost, axis, bins left of the plane)
    for axis in 0..3 {
        if extent[axis] <= 0.0 {
            continue;
        }
        let bin_of = |p: &Point3<f64>| {
            (((p[axis] - centroid_bounds.min[axis]) / extent[axis] * BINS as f64) as usize)
                .min(BINS - 1)
        };
        let mut bin_bounds = [Aabb::empty(); BINS];
        let mut bin_counts = [0usize; BINS];
        for &i in order.iter() {
            let b = bin_of(&centroids[i as usize]);
            bin_bounds[b].grow(&bounds[i as usize]);
            bin_counts[b] += 1;
        }
        // Sweep from the right to get the cost of every plane between bins.
        let mut right_area = [0.0; BINS];
        let mut right_count = [0usize; BINS];
        let mut acc = Aabb::empty();
        let mut n = 0;
        for b in (1..BINS).rev() {
            acc.grow(&bin_bounds[b]);
            n += bin_counts[b];
            right_area[b] = acc.half_area();
            right_count[b] = n;
        }
        let mut acc = Aabb::empty();
        let mut n = 0;
        let parent_area = node_bounds.half_area().max(1e-300);
        for plane in 1..BINS {
            acc.grow(&bin_bounds[plane - 1]);
            n += bin_counts[plane - 1];
            if n == 0 || right_count[plane] == 0 {
                continue;
            }
            let cost = TRAVERSAL_COST
                + (acc.half_area() * n as f64 + right_area[plane] * right_count[plane] as f64)
                    / parent_area;
            if best.is_none_or(|(c, _, _)| cost < c) {
                best = Some((cost, axis, plane));
            }
        }
    }
    match best {
        Some((cost, axis, plane)) if cost < leaf_cost || count > 4 * MAX_LEAF => {
            let threshold = |p: &Point3<f64>| {
                let b = (((p[axis] - centroid_bounds.min[axis]) / extent[axis] * BINS as f64)
                    as usize)
                    .min(BINS - 1);
                b < plane
            };
            let mut mid = 0;
            for k in 0..count {
                if threshold(&centroids[order[k] as usize]) {
                    order.swap(k, mid);
                    mid += 1;
                }
            }
            (mid > 0 && mid < count).then_some(mid)
        }
        Some(_) => None,
        // All centroids coincide: split by index so large clumps still get a tree.
        None if count > 4 * MAX_LEAF => Some(count / 2),
        None => None,
    }
}
