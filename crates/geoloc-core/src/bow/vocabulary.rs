//! The visual vocabulary: a tree of up to `branching`ᵈᵉᵖᵗʰ words built by hierarchical
//! clustering of local descriptors (Nistér & Stewénius 2006; DBoW2): k-means++ seeding (each
//! next seed drawn with probability ∝ D(x)², D = [`Row::distance`], the nearest seed's
//! distance) and Lloyd iterations per node, with Euclidean distance and mean centres for float
//! descriptors (SIFT) and Hamming distance and bitwise-majority centres (k-majority) for
//! binary ones (ORB). A descriptor's word is found by descending to the nearest child at
//! each level. The tree is built iteratively (depth-first, so word ids follow the
//! recursion's order), with `branching` ≤ [`MAX_BRANCHING`], `depth` ≤ [`MAX_DEPTH`] and
//! `branching`ᵈᵉᵖᵗʰ ≤ [`MAX_WORDS`]. Its flat-array form for map files is [`super::arrays`].

use super::TermWeighting;
use crate::error::{GeolocError, Result};
use crate::matching::{DescriptorSet, Descriptors, Row};
use crate::parallel::{map_indices, map_slice};
use crate::rng::SplitMix64;

/// Largest `branching` [`Vocabulary::train`] accepts.
pub const MAX_BRANCHING: usize = 1024;
/// Largest `depth` [`Vocabulary::train`] accepts.
pub const MAX_DEPTH: usize = 24;
/// Largest `branching`ᵈᵉᵖᵗʰ [`Vocabulary::train`] accepts (16.7 M words; DBoW2's largest
/// published vocabularies have 10⁶).
pub const MAX_WORDS: usize = 1 << 24;
/// Lloyd iterations per tree node.
const LLOYD_ITERATIONS: usize = 10;
/// Cluster members below which a k-means step (seeding, assignment) stays on the calling
/// thread; above, each member's distances run in parallel and the results are combined in
/// member order, so the vocabulary is the same with any thread count.
const KMEANS_PARALLEL_MIN: usize = 4096;
/// Descriptors below which [`Vocabulary::words_of`] stays on the calling thread.
const WORDS_PARALLEL_MIN: usize = 64;

/// The centre nearest to `row` (the first on ties): one distance per centre.
fn nearest_centre(row: &Row<'_>, centres: &Descriptors<'_>) -> usize {
    let (mut best, mut best_d) = (0, f32::INFINITY);
    for c in 0..centres.len() {
        let d = row.distance(&centres.row(c));
        if d < best_d {
            (best, best_d) = (c, d);
        }
    }
    best
}
/// Centre of `members` (k-majority bits or means).
fn centre_of(desc: &Descriptors<'_>, members: &[usize]) -> DescriptorSet {
    match *desc {
        Descriptors::Binary { data, width } => {
            // one pass over the members, counting the ones of every bit (row-major reads)
            let mut ones = vec![0usize; 8 * width];
            for &m in members {
                for (byte, &value) in data[m * width..(m + 1) * width].iter().enumerate() {
                    for bit in 0..8 {
                        ones[8 * byte + bit] += usize::from(value >> bit & 1);
                    }
                }
            }
            let mut out = vec![0u8; width];
            for (i, &count) in ones.iter().enumerate() {
                if 2 * count > members.len() {
                    out[i / 8] |= 1 << (i % 8);
                }
            }
            DescriptorSet::Binary { data: out, width }
        }
        Descriptors::Float { data, width } => {
            let mut out = vec![0f32; width];
            for &m in members {
                for (o, v) in out.iter_mut().zip(&data[m * width..(m + 1) * width]) {
                    *o += v;
                }
            }
            let n = members.len().max(1) as f32;
            out.iter_mut().for_each(|o| *o /= n);
            DescriptorSet::Float { data: out, width }
        }
    }
}

/// One node of the vocabulary tree: the centres of its children and where they lead.
#[derive(Clone, Debug, PartialEq)]
pub(super) struct Node {
    pub(super) centres: DescriptorSet,
    /// Per child: another node, or a word (leaf).
    pub(super) children: Vec<Child>,
}

#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) enum Child {
    Node(usize),
    Word(u32),
}

/// A node whose clusters are being turned into children (the explicit stack of the build).
struct Pending {
    node: usize,
    clusters: std::vec::IntoIter<Vec<usize>>,
    /// Levels left below this node's children.
    depth_left: usize,
    /// How many members the node split.
    members: usize,
}

/// A hierarchical visual vocabulary.
#[derive(Clone, Debug, PartialEq)]
pub struct Vocabulary {
    pub(super) nodes: Vec<Node>,
    pub(super) words: usize,
    pub(super) binary: bool,
    pub(super) width: usize,
}

/// The checks of [`Vocabulary::train`].
fn check_training(descriptors: &Descriptors<'_>, branching: usize, depth: usize) -> Result<()> {
    descriptors.check("descriptors")?;
    if !(2..=MAX_BRANCHING).contains(&branching) {
        return Err(GeolocError::invalid("branching", format!("must be in 2..={MAX_BRANCHING}, got {branching}")));
    }
    if !(1..=MAX_DEPTH).contains(&depth) {
        return Err(GeolocError::invalid("depth", format!("must be in 1..={MAX_DEPTH}, got {depth}")));
    }
    let words = u32::try_from(depth).ok().and_then(|d| branching.checked_pow(d));
    if words.is_none_or(|w| w > MAX_WORDS) {
        return Err(GeolocError::invalid(
            "depth",
            format!("branching^depth = {branching}^{depth} exceeds the limit of {MAX_WORDS} words"),
        ));
    }
    let n = descriptors.len();
    if n < branching {
        return Err(GeolocError::invalid("descriptors", format!("{n} descriptors cannot make {branching} clusters")));
    }
    Ok(())
}

impl Vocabulary {
    /// Clusters `descriptors` into a tree of up to `branching`^`depth` words (seeded).
    ///
    /// # Errors
    /// `branching` outside 2..=[`MAX_BRANCHING`], `depth` outside 1..=[`MAX_DEPTH`],
    /// `branching`^`depth` above [`MAX_WORDS`] (named `depth`), fewer descriptors than
    /// `branching`, a zero width or non-finite float values (named `descriptors`).
    pub fn train(descriptors: &Descriptors<'_>, branching: usize, depth: usize, seed: u64) -> Result<Self> {
        check_training(descriptors, branching, depth)?;
        let mut vocabulary =
            Self { nodes: Vec::new(), words: 0, binary: descriptors.is_binary(), width: descriptors.width() };
        let mut rng = SplitMix64::new(seed);
        let all: Vec<usize> = (0..descriptors.len()).collect();
        let mut stack = vec![vocabulary.split(descriptors, &all, branching, depth, &mut rng)];
        // depth-first, children in cluster order: the order of the recursive definition
        while let Some(top) = stack.last_mut() {
            let Some(cluster) = top.clusters.next() else {
                stack.pop();
                continue;
            };
            let (parent, depth_left, parent_members) = (top.node, top.depth_left, top.members);
            // a cluster holding all of its parent's members (identical descriptors) cannot split
            let child = if depth_left > 0 && cluster.len() > branching && cluster.len() < parent_members {
                let pending = vocabulary.split(descriptors, &cluster, branching, depth_left, &mut rng);
                let index = pending.node;
                stack.push(pending);
                Child::Node(index)
            } else {
                vocabulary.words += 1;
                Child::Word((vocabulary.words - 1) as u32)
            };
            vocabulary.nodes[parent].children.push(child);
        }
        Ok(vocabulary)
    }

    /// Clusters `members` into a new node with `depth` levels (this one included).
    fn split(
        &mut self,
        desc: &Descriptors<'_>,
        members: &[usize],
        branching: usize,
        depth: usize,
        rng: &mut SplitMix64,
    ) -> Pending {
        let k = branching.min(members.len());
        let seeds = seed_centres(desc, members, k, rng);
        let (centres, clusters) = lloyd(desc, members, &seeds);
        let node = self.nodes.len();
        self.nodes.push(Node { centres, children: Vec::with_capacity(k) });
        Pending { node, clusters: clusters.into_iter(), depth_left: depth - 1, members: members.len() }
    }

    /// Number of words (leaves).
    pub fn len(&self) -> usize {
        self.words
    }

    /// Whether the vocabulary has no words (never after training).
    pub fn is_empty(&self) -> bool {
        self.words == 0
    }

    /// Whether the vocabulary is for binary descriptors.
    pub fn is_binary(&self) -> bool {
        self.binary
    }

    /// The term weighting of a database over this vocabulary: [`TermWeighting::Count`] for
    /// binary descriptors, [`TermWeighting::Presence`] for float ones (see the module doc).
    pub fn term_weighting(&self) -> TermWeighting {
        if self.binary { TermWeighting::Count } else { TermWeighting::Presence }
    }

    /// The word of one descriptor: descend to the nearest child at each level.
    fn word_of(&self, row: &Row<'_>) -> u32 {
        let mut node = 0;
        loop {
            let n = &self.nodes[node];
            match n.children[nearest_centre(row, &n.centres.view())] {
                Child::Node(next) => node = next,
                Child::Word(w) => return w,
            }
        }
    }

    /// The word of each descriptor (parallel over descriptors; see [`crate::parallel`]).
    ///
    /// # Errors
    /// Descriptors of the other kind or width than the vocabulary's, or non-finite values.
    pub fn words_of(&self, descriptors: &Descriptors<'_>) -> Result<Vec<u32>> {
        descriptors.check("descriptors")?;
        if descriptors.is_binary() != self.binary || descriptors.width() != self.width {
            return Err(GeolocError::invalid(
                "descriptors",
                format!(
                    "the vocabulary is for {} descriptors of width {}",
                    if self.binary { "binary" } else { "float" },
                    self.width
                ),
            ));
        }
        Ok(map_indices(descriptors.len(), WORDS_PARALLEL_MIN, |i| self.word_of(&descriptors.row(i))))
    }
}

/// k-means++ seeding (Arthur & Vassilvitskii 2007): the first seed uniform over `members`,
/// each next one drawn with probability D(x)² / Σ_y D(y)², D(x) the [`Row::distance`] from x
/// to its nearest seed so far. Returns the seeds (descriptor indices).
fn seed_centres(desc: &Descriptors<'_>, members: &[usize], k: usize, rng: &mut SplitMix64) -> Vec<usize> {
    let mut seeds = vec![members[(rng.next_u64() % members.len() as u64) as usize]];
    let mut nearest: Vec<f32> = vec![f32::INFINITY; members.len()];
    while seeds.len() < k {
        let last = desc.row(*seeds.last().expect("invariant: one seed"));
        // distances in parallel (each slot on its own), the total in member order
        nearest =
            map_indices(members.len(), KMEANS_PARALLEL_MIN, |i| nearest[i].min(desc.row(members[i]).distance(&last)));
        let total: f64 = nearest.iter().fold(0.0, |t, &d| t + f64::from(d) * f64::from(d));
        let mut target = rng.uniform() * total;
        let mut pick = members[members.len() - 1];
        for (&d, &m) in nearest.iter().zip(members) {
            target -= f64::from(d) * f64::from(d);
            if target <= 0.0 {
                pick = m;
                break;
            }
        }
        seeds.push(pick);
    }
    seeds
}

/// Lloyd iterations from `seeds` over `members`; returns the centres and the clusters (an
/// empty cluster keeps its seed as centre).
fn lloyd(desc: &Descriptors<'_>, members: &[usize], seeds: &[usize]) -> (DescriptorSet, Vec<Vec<usize>>) {
    let k = seeds.len();
    let mut centres = DescriptorSet::stack(&seeds.iter().map(|&s| centre_of(desc, &[s])).collect::<Vec<_>>());
    let mut clusters = vec![Vec::new(); k];
    for _ in 0..LLOYD_ITERATIONS {
        clusters = vec![Vec::new(); k];
        let view = centres.view();
        let assigned = map_slice(members, KMEANS_PARALLEL_MIN, |&m| nearest_centre(&desc.row(m), &view));
        for (&m, c) in members.iter().zip(assigned) {
            clusters[c].push(m);
        }
        let next = DescriptorSet::stack(
            &clusters
                .iter()
                .zip(seeds)
                .map(|(c, &seed)| if c.is_empty() { centre_of(desc, &[seed]) } else { centre_of(desc, c) })
                .collect::<Vec<_>>(),
        );
        if next == centres {
            break;
        }
        centres = next;
    }
    (centres, clusters)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::stats::chi2::CHI2_19_999;

    /// The k-majority centre against a bit-by-bit reference (bit b of byte i is set when more
    /// than half of the members have it; exactly half is not a majority), members repeated
    /// and in any order; the float centre is the arithmetic mean.
    #[test]
    fn centres_match_bitwise_majority_and_the_mean() {
        let mut rng = SplitMix64::new(11);
        let (n, width) = (37, 5);
        let data: Vec<u8> = (0..n * width).map(|_| (rng.next_u64() & 0xff) as u8).collect();
        let d = Descriptors::Binary { data: &data, width };
        for members in [vec![0, 1], vec![3, 3, 7], (0..n).collect(), (0..n).rev().step_by(3).collect::<Vec<_>>()] {
            let mut expected = vec![0u8; width];
            for (byte, out) in expected.iter_mut().enumerate() {
                for bit in 0..8 {
                    let ones = members.iter().filter(|&&m| data[m * width + byte] & (1 << bit) != 0).count();
                    if ones * 2 > members.len() {
                        *out |= 1 << bit;
                    }
                }
            }
            assert_eq!(centre_of(&d, &members), DescriptorSet::Binary { data: expected, width }, "{members:?}");
        }
        let floats = [1.0f32, 2.0, 3.0, 5.0, -4.0, 0.5];
        let f = Descriptors::Float { data: &floats, width: 2 };
        assert_eq!(centre_of(&f, &[0, 1, 2]), DescriptorSet::Float { data: vec![0.0, 2.5], width: 2 });
    }

    /// The nearest centre is the first of equally near ones (centres 0 = 2 and 1 = 3).
    #[test]
    fn nearest_centre_takes_the_first_on_ties() {
        let centres = [0u8, 3, 0, 3];
        let c = Descriptors::Binary { data: &centres, width: 1 };
        assert_eq!(nearest_centre(&Row::Binary(&[1]), &c), 0);
        assert_eq!(nearest_centre(&Row::Binary(&[2]), &c), 0);
        assert_eq!(nearest_centre(&Row::Binary(&[7]), &c), 1);
        assert_eq!(nearest_centre(&Row::Binary(&[0]), &c), 0);
    }

    /// Seeding and assignment run in parallel above [`KMEANS_PARALLEL_MIN`] members: the
    /// vocabulary (every descriptor's word) is the same with one and with two threads.
    #[test]
    fn vocabulary_is_identical_with_one_or_two_threads() {
        use crate::parallel::{Parallelism, with_parallelism};
        use std::num::NonZero;
        let mut rng = SplitMix64::new(5);
        let n = 3 * KMEANS_PARALLEL_MIN;
        let bytes: Vec<u8> = (0..n * 32).map(|_| (rng.next_u64() & 0xff) as u8).collect();
        let floats: Vec<f32> = (0..n * 8).map(|_| rng.normal() as f32).collect();
        for d in [Descriptors::Binary { data: &bytes, width: 32 }, Descriptors::Float { data: &floats, width: 8 }] {
            let words = |threads: usize| {
                let p = Parallelism::Threads(NonZero::new(threads).expect("positive"));
                with_parallelism(&p, || Vocabulary::train(&d, 6, 2, 3).and_then(|v| v.words_of(&d))).expect("valid")
            };
            assert_eq!(words(1), words(2));
        }
    }

    /// k-means++ draws the second seed with probability D²/ΣD² (D the distance to the first
    /// seed): the observed frequencies of (first, second) seed pairs over many seeded draws
    /// against the closed form P(i, j) = (1/n) · D_ij² / Σ_l D_il², by a χ² test; the D⁴
    /// weighting (the old bug) is rejected by the same test.
    #[test]
    fn kmeanspp_seeding_follows_d_squared() {
        let xs = [0.0f32, 1.0, 2.0, 4.0, 8.0];
        let n = xs.len();
        let d = Descriptors::Float { data: &xs, width: 1 };
        let members: Vec<usize> = (0..n).collect();
        let trials = 40_000;
        let mut counts = vec![0usize; n * n];
        let mut rng = SplitMix64::new(2024);
        for _ in 0..trials {
            let seeds = seed_centres(&d, &members, 2, &mut rng);
            counts[seeds[0] * n + seeds[1]] += 1;
        }
        let chi2 = |power: i32| -> f64 {
            let mut chi2 = 0.0;
            for i in 0..n {
                let w: Vec<f64> = xs.iter().map(|&x| f64::from((x - xs[i]).abs()).powi(power)).collect();
                let total: f64 = w.iter().sum();
                for j in 0..n {
                    let expected = trials as f64 / n as f64 * w[j] / total;
                    if expected > 0.0 {
                        chi2 += (counts[i * n + j] as f64 - expected).powi(2) / expected;
                    } else {
                        assert_eq!(counts[i * n + j], 0, "a zero-probability pair ({i}, {j}) was drawn");
                    }
                }
            }
            chi2
        };
        // 20 cells with positive probability, 19 degrees of freedom: χ²₁₉(0.999) = 43.82
        let (d2, d4) = (chi2(2), chi2(4));
        assert!(d2 < CHI2_19_999, "D² seeding rejected: χ² = {d2}");
        assert!(d4 > 10.0 * CHI2_19_999, "the test cannot tell D⁴ from D²: χ² = {d4}");
    }

    /// Binary descriptors use the same D² law, D the Hamming distance.
    #[test]
    fn kmeanspp_binary_weights_are_hamming_squared() {
        // rows at Hamming distance 0, 1, 3 and 8 from row 0
        let rows = [0x00u8, 0x01, 0x07, 0xff];
        let d = Descriptors::Binary { data: &rows, width: 1 };
        let members = [0usize, 1, 2, 3];
        let (mut seen, mut rng) = ([0usize; 4], SplitMix64::new(9));
        let mut firsts = 0;
        while firsts < 20_000 {
            let seeds = seed_centres(&d, &members, 2, &mut rng);
            if seeds[0] == 0 {
                seen[seeds[1]] += 1;
                firsts += 1;
            }
        }
        let total: f64 = 1.0 + 9.0 + 64.0;
        for (j, w) in [(1, 1.0_f64), (2, 9.0), (3, 64.0)] {
            let p = f64::from(seen[j] as u32) / 20_000.0;
            let want = w / total;
            let sigma = (want * (1.0 - want) / 20_000.0).sqrt();
            assert!((p - want).abs() < 4.0 * sigma, "row {j}: {p} vs {want}");
        }
        assert_eq!(seen[0], 0);
    }

    /// Depth and branching come from the caller: capped, and the build is iterative (50
    /// identical descriptors used to recurse 20 000 levels deep and overflow the stack).
    #[test]
    fn depth_and_branching_are_capped() {
        let zeros = [0u8; 50 * 32];
        let d = Descriptors::Binary { data: &zeros, width: 32 };
        let named = |r: Result<Vocabulary>, want: &str| match r {
            Err(GeolocError::InvalidInput { name, .. }) => assert_eq!(name, want),
            other => panic!("expected InvalidInput({want}), got {other:?}"),
        };
        named(Vocabulary::train(&d, 2, 20_000, 0), "depth");
        named(Vocabulary::train(&d, 2, 0, 0), "depth");
        named(Vocabulary::train(&d, MAX_BRANCHING + 1, 2, 0), "branching");
        named(Vocabulary::train(&d, 1, 2, 0), "branching");
        named(Vocabulary::train(&d, 1000, 3, 0), "depth"); // 10⁹ words
        let v = Vocabulary::train(&d, 2, MAX_DEPTH, 0).expect("identical descriptors at the deepest depth");
        assert!(!v.is_empty() && v.len() <= 2);
        let nan = [f32::NAN; 8];
        match Vocabulary::train(&Descriptors::Float { data: &nan, width: 4 }, 2, 1, 0) {
            Err(GeolocError::NonFinite { name, index }) => assert_eq!((name.as_str(), index), ("descriptors", 0)),
            other => panic!("{other:?}"),
        }
    }

    /// The weighting per descriptor kind: counts for binary (ORB, unchanged), presence for
    /// float (SIFT).
    #[test]
    fn term_weighting_follows_the_descriptor_kind() {
        let mut rng = SplitMix64::new(4);
        let bytes: Vec<u8> = (0..64 * 4).map(|_| rng.next_u64() as u8).collect();
        let floats: Vec<f32> = (0..64 * 4).map(|_| rng.normal() as f32).collect();
        let binary = Vocabulary::train(&Descriptors::Binary { data: &bytes, width: 4 }, 4, 2, 0).expect("valid");
        let float = Vocabulary::train(&Descriptors::Float { data: &floats, width: 4 }, 4, 2, 0).expect("valid");
        assert_eq!((binary.is_binary(), binary.term_weighting()), (true, TermWeighting::Count));
        assert_eq!((float.is_binary(), float.term_weighting()), (false, TermWeighting::Presence));
    }
}
