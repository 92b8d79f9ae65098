//! The correspondence graph: for every keypoint of every image, the keypoints of
//! other images it was matched to (verified inliers only), and the tracks that
//! these links form.
//!
//! Storage is CSR-like over a global keypoint index (images in id order, each
//! image's keypoints contiguous), built once and read-only afterwards.
use std::collections::BTreeMap;

use super::ids::{ImageId, Point2DIdx};
use super::reconstruction::TrackElement;

/// One side of a verified match.
pub type Correspondence = TrackElement;

#[derive(Clone, Debug, Default)]
pub struct CorrespondenceGraph {
    /// Global index of each image's first keypoint, and its keypoint count.
    images: BTreeMap<ImageId, (usize, usize)>,
    /// `corr_start[g]..corr_start[g + 1]` indexes `corrs` for global keypoint `g`.
    corr_start: Vec<usize>,
    corrs: Vec<Correspondence>,
    /// Number of verified matches per image pair (smaller id first).
    pair_matches: BTreeMap<(ImageId, ImageId), usize>,
}

/// Summary of the tracks (connected components of the graph).
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct TrackStats {
    /// `histogram[n]` = number of tracks seen in exactly `n` distinct images.
    pub histogram: BTreeMap<usize, usize>,
    pub num_tracks: usize,
    /// Tracks holding two or more keypoints of one image (ambiguous).
    pub num_inconsistent: usize,
}

impl CorrespondenceGraph {
    /// Builds the graph from the keypoint count of every image and the verified
    /// inlier matches of every pair. Matches must index existing keypoints (the
    /// database reader checks this); out-of-range matches are skipped.
    pub fn new<'a>(
        keypoint_counts: impl IntoIterator<Item = (ImageId, usize)>,
        pairs: impl IntoIterator<Item = (ImageId, ImageId, &'a [[u32; 2]])> + Clone,
    ) -> Self {
        let mut images = BTreeMap::new();
        let mut total = 0usize;
        let mut counts: Vec<(ImageId, usize)> = keypoint_counts.into_iter().collect();
        counts.sort();
        for (id, n) in counts {
            images.insert(id, (total, n));
            total += n;
        }
        let global = |images: &BTreeMap<ImageId, (usize, usize)>, id: ImageId, idx: u32| {
            images
                .get(&id)
                .and_then(|&(start, n)| ((idx as usize) < n).then_some(start + idx as usize))
        };
        // Pass 1: degree of every keypoint.
        let mut degree = vec![0usize; total + 1];
        let mut pair_matches = BTreeMap::new();
        for (a, b, matches) in pairs.clone() {
            if a == b {
                continue;
            }
            let mut kept = 0;
            for m in matches {
                if let (Some(ga), Some(gb)) = (global(&images, a, m[0]), global(&images, b, m[1])) {
                    degree[ga] += 1;
                    degree[gb] += 1;
                    kept += 1;
                }
            }
            if kept > 0 {
                let key = if a < b { (a, b) } else { (b, a) };
                *pair_matches.entry(key).or_insert(0) += kept;
            }
        }
        let mut corr_start = vec![0usize; total + 1];
        for g in 0..total {
            corr_start[g + 1] = corr_start[g] + degree[g];
        }
        // Pass 2: fill.
        let mut fill = corr_start.clone();
        let mut corrs = vec![
            TrackElement {
                image_id: ImageId(0),
                point2d_idx: 0
            };
            corr_start[total]
        ];
        for (a, b, matches) in pairs {
            if a == b {
                continue;
            }
            for m in matches {
                if let (Some(ga), Some(gb)) = (global(&images, a, m[0]), global(&images, b, m[1])) {
                    corrs[fill[ga]] = TrackElement {
                        image_id: b,
                        point2d_idx: m[1],
                    };
                    fill[ga] += 1;
                    corrs[fill[gb]] = TrackElement {
                        image_id: a,
                        point2d_idx: m[0],
                    };
                    fill[gb] += 1;
                }
            }
        }
        // Sorted, duplicate-free lists make every later traversal deterministic.
        let mut dedup = Vec::with_capacity(corrs.len());
        let mut new_start = vec![0usize; total + 1];
        for g in 0..total {
            let mut list = corrs[corr_start[g]..corr_start[g + 1]].to_vec();
            list.sort();
            list.dedup();
            dedup.extend_from_slice(&list);
            new_start[g + 1] = dedup.len();
        }
        Self {
            images,
            corr_start: new_start,
            corrs: dedup,
            pair_matches,
        }
    }

    pub fn num_images(&self) -> usize {
        self.images.len()
    }

    pub fn image_ids(&self) -> impl Iterator<Item = ImageId> + '_ {
        self.images.keys().copied()
    }

    pub fn num_keypoints(&self, image: ImageId) -> usize {
        self.images.get(&image).map_or(0, |&(_, n)| n)
    }

    fn global(&self, image: ImageId, idx: Point2DIdx) -> Option<usize> {
        let &(start, n) = self.images.get(&image)?;
        ((idx as usize) < n).then_some(start + idx as usize)
    }

    /// The keypoints matched to keypoint `idx` of `image`, sorted by image and index.
    pub fn correspondences(&self, image: ImageId, idx: Point2DIdx) -> &[Correspondence] {
        match self.global(image, idx) {
            Some(g) => &self.corrs[self.corr_start[g]..self.corr_start[g + 1]],
            None => &[],
        }
    }

    /// Number of keypoints of `image` with at least one correspondence.
    pub fn num_observations(&self, image: ImageId) -> usize {
        let Some(&(start, n)) = self.images.get(&image) else {
            return 0;
        };
        (start..start + n)
            .filter(|&g| self.corr_start[g + 1] > self.corr_start[g])
            .count()
    }

    /// Verified matches between two images (either order).
    pub fn num_matches_between(&self, a: ImageId, b: ImageId) -> usize {
        let key = if a < b { (a, b) } else { (b, a) };
        self.pair_matches.get(&key).copied().unwrap_or(0)
    }

    /// The image graph's connected components over `images` (images linked
    /// by verified pairs): each image's group, named by the group's smallest
    /// image id. An image without a pair is a group of its own; pairs with an
    /// image not in `images` are ignored.
    pub fn image_groups(
        &self,
        images: impl IntoIterator<Item = ImageId>,
    ) -> BTreeMap<ImageId, ImageId> {
        // Union-find; a root is always the smaller of the two it joins.
        let mut parent: BTreeMap<ImageId, ImageId> =
            images.into_iter().map(|id| (id, id)).collect();
        // With path halving: each step points a node at its grandparent.
        fn root(parent: &mut BTreeMap<ImageId, ImageId>, mut id: ImageId) -> ImageId {
            while parent[&id] != id {
                let grand = parent[&parent[&id]];
                parent.insert(id, grand);
                id = grand;
            }
            id
        }
        for (&(a, b), &n) in &self.pair_matches {
            if n == 0 || !parent.contains_key(&a) || !parent.contains_key(&b) {
                continue;
            }
            let (ra, rb) = (root(&mut parent, a), root(&mut parent, b));
            parent.insert(ra.max(rb), ra.min(rb));
        }
        let ids: Vec<ImageId> = parent.keys().copied().collect();
        ids.into_iter()
            .map(|id| (id, root(&mut parent, id)))
            .collect()
    }

    /// The size of each group of [`Self::image_groups`]' result, by name.
    pub fn group_sizes(groups: &BTreeMap<ImageId, ImageId>) -> BTreeMap<ImageId, usize> {
        let mut sizes: BTreeMap<ImageId, usize> = BTreeMap::new();
        for g in groups.values() {
            *sizes.entry(*g).or_default() += 1;
        }
        sizes
    }

    /// Image pairs with their verified match counts, smaller id first.
    pub fn pairs(&self) -> impl Iterator<Item = ((ImageId, ImageId), usize)> + '_ {
        self.pair_matches.iter().map(|(k, v)| (*k, *v))
    }

    /// Connected components with two or more keypoints, each sorted, in order of
    /// their smallest element.
    pub fn tracks(&self) -> Vec<Vec<TrackElement>> {
        let total = self.corr_start.len() - 1;
        let mut parent: Vec<usize> = (0..total).collect();
        fn find(parent: &mut [usize], mut x: usize) -> usize {
            while parent[x] != x {
                parent[x] = parent[parent[x]];
                x = parent[x];
            }
            x
        }
        for g in 0..total {
            for c in &self.corrs[self.corr_start[g]..self.corr_start[g + 1]] {
                if let Some(h) = self.global(c.image_id, c.point2d_idx) {
                    let (ra, rb) = (find(&mut parent, g), find(&mut parent, h));
                    if ra != rb {
                        parent[ra.max(rb)] = ra.min(rb);
                    }
                }
            }
        }
        let mut by_root: BTreeMap<usize, Vec<usize>> = BTreeMap::new();
        for g in 0..total {
            if self.corr_start[g + 1] > self.corr_start[g] {
                let r = find(&mut parent, g);
                by_root.entry(r).or_default().push(g);
            }
        }
        let image_starts: Vec<(usize, ImageId)> = self
            .images
            .iter()
            .map(|(&id, &(start, _))| (start, id))
            .collect();
        let to_element = |g: usize| {
            let k = image_starts.partition_point(|&(start, _)| start <= g) - 1;
            let (start, image_id) = image_starts[k];
            TrackElement {
                image_id,
                point2d_idx: (g - start) as u32,
            }
        };
        by_root
            .into_values()
            .map(|gs| gs.into_iter().map(to_element).collect())
            .collect()
    }

    /// Track-length statistics (lengths in distinct images).
    pub fn track_stats(&self) -> TrackStats {
        let mut stats = TrackStats::default();
        for track in self.tracks() {
            let mut ids: Vec<ImageId> = track.iter().map(|e| e.image_id).collect();
            ids.dedup(); // sorted by image already
            if ids.len() < track.len() {
                stats.num_inconsistent += 1;
            }
            *stats.histogram.entry(ids.len()).or_insert(0) += 1;
            stats.num_tracks += 1;
        }
        stats
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn te(i: u32, k: u32) -> TrackElement {
        TrackElement {
            image_id: ImageId(i),
            point2d_idx: k,
        }
    }

    #[test]
    fn image_groups_are_the_connected_components_named_by_their_smallest_id() {
        // 5-3, 3-1 (joined through 3), 2-4, 6 alone; 7 has a pair with 8,
        // which is not asked about.
        let m: Vec<[u32; 2]> = vec![[0, 0]];
        let pairs: Vec<(ImageId, ImageId, &[[u32; 2]])> = [(3, 5), (1, 3), (2, 4), (7, 8)]
            .into_iter()
            .map(|(a, b)| (ImageId(a), ImageId(b), m.as_slice()))
            .collect();
        let g = CorrespondenceGraph::new((1..=8).map(|i| (ImageId(i), 1)), pairs);
        let groups = g.image_groups((1..=7).map(ImageId));
        let named: Vec<(u32, u32)> = groups.iter().map(|(a, b)| (a.0, b.0)).collect();
        assert_eq!(
            named,
            vec![(1, 1), (2, 2), (3, 1), (4, 2), (5, 1), (6, 6), (7, 7)]
        );
        let sizes = CorrespondenceGraph::group_sizes(&groups);
        let sizes: Vec<(u32, usize)> = sizes.iter().map(|(g, n)| (g.0, *n)).collect();
        assert_eq!(sizes, vec![(1, 3), (2, 2), (6, 1), (7, 1)]);
    }

    #[test]
    fn hand_made_graph() {
        // Three images; keypoint 0 of image 1 is seen in images 2 (kp 3) and 3 (kp 1),
        // and image 2 kp 3 <-> image 3 kp 1 closes the triangle. Image 1 kp 1 <-> image 2 kp 0.
        let m12: Vec<[u32; 2]> = vec![[0, 3], [1, 0]];
        let m13: Vec<[u32; 2]> = vec![[0, 1]];
        let m23: Vec<[u32; 2]> = vec![[3, 1], [9, 9]]; // the second is out of range: skipped
        let pairs = vec![
            (ImageId(1), ImageId(2), m12.as_slice()),
            (ImageId(1), ImageId(3), m13.as_slice()),
            (ImageId(2), ImageId(3), m23.as_slice()),
        ];
        let g =
            CorrespondenceGraph::new([(ImageId(1), 2), (ImageId(2), 4), (ImageId(3), 2)], pairs);
        assert_eq!(g.correspondences(ImageId(1), 0), &[te(2, 3), te(3, 1)]);
        assert_eq!(g.correspondences(ImageId(3), 1), &[te(1, 0), te(2, 3)]);
        assert_eq!(g.correspondences(ImageId(3), 0), &[]);
        assert_eq!(g.num_matches_between(ImageId(3), ImageId(2)), 1);
        assert_eq!(g.num_matches_between(ImageId(1), ImageId(2)), 2);
        assert_eq!(g.num_observations(ImageId(2)), 2);
        let tracks = g.tracks();
        assert_eq!(
            tracks,
            vec![vec![te(1, 0), te(2, 3), te(3, 1)], vec![te(1, 1), te(2, 0)]]
        );
        let stats = g.track_stats();
        assert_eq!(stats.num_tracks, 2);
        assert_eq!(stats.histogram, BTreeMap::from([(2, 1), (3, 1)]));
        assert_eq!(stats.num_inconsistent, 0);
    }

    #[test]
    fn inconsistent_track_is_counted() {
        // Image 1 kp 0 and kp 1 both match image 2 kp 0: one track, two keypoints of image 1.
        let m: Vec<[u32; 2]> = vec![[0, 0], [1, 0]];
        let g = CorrespondenceGraph::new(
            [(ImageId(1), 2), (ImageId(2), 1)],
            vec![(ImageId(1), ImageId(2), m.as_slice())],
        );
        let stats = g.track_stats();
        assert_eq!(stats.num_tracks, 1);
        assert_eq!(stats.num_inconsistent, 1);
        assert_eq!(stats.histogram, BTreeMap::from([(2, 1)]));
    }
}
