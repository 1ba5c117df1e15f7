//! Bag-of-visual-words retrieval (the paper's "BoW + Locator" baseline, and geoloc's default
//! when no descriptor network is given — it needs no training framework).
//!
//! * **Vocabulary**: a tree of up to `branching`ᵈᵉᵖᵗʰ words built by hierarchical clustering
//!   of local descriptors (Nistér & Stewénius 2006; DBoW2): k-means++ seeding (each next seed
//!   drawn with probability ∝ D(x)², D = [`Row::distance`], the nearest seed's distance) and
//!   Lloyd iterations per node, with Euclidean distance and mean centres for float
//!   descriptors (SIFT) and Hamming distance and bitwise-majority centres (k-majority) for
//!   binary ones (ORB). A descriptor's word is found by descending to the nearest child at
//!   each level. The tree is built iteratively (depth-first, so word ids follow the
//!   recursion's order), with `branching` ≤ [`MAX_BRANCHING`], `depth` ≤ [`MAX_DEPTH`] and
//!   `branching`ᵈᵉᵖᵗʰ ≤ [`MAX_WORDS`].
//! * **Database**: TF-IDF vectors vᵢ,w = tfᵢ,w · ln(N / n_w) (N images, n_w of them containing
//!   w), L1-normalized, in an inverted file; the score of two images is the L1 similarity
//!   s = 1 − ½‖v − u‖₁ = Σ_w min(v_w, u_w) ∈ [0, 1] (DBoW2's; the weights are ≥ 0), summed
//!   over the words they share.
//! * **Term weighting per descriptor kind** ([`Vocabulary::term_weighting`], used by the map,
//!   its file and the Python `BowDatabase`): tf = the count n for binary descriptors (ORB,
//!   DBoW2's; unchanged), tf = [n > 0] (presence) for float ones (SIFT, RootSIFT). SIFT's DoG
//!   detector fires all over repetitive texture (7-Scenes redkitchen's striped carpet): 41–57
//!   descriptors of one keyframe in one word (fold 0–99, 10³ words), against 7–16 for ORB,
//!   which keeps its n best Harris corners. With tf = n those bursts dominated the L1 score, so every image with carpet
//!   in view (frames 0–133) scored ~0.56 against every other (median 0.24) and one keyframe
//!   was the first match of 31–59 of 100 queries; counting presence removes the burst
//!   (Jégou, Douze & Schmid 2009, "On the burstiness of visual elements";
//!   `benchmarks/retrieval_ranks.py`). ORB's ranking, measured, is better with tf = n.
//!   Both kinds use `branching`ᵈᵉᵖᵗʰ = 10³ words by default (10⁴ changed neither kind's
//!   ranking materially on the folds measured).
//!
//! Reproducibility: vectors are sorted by word, every sum runs in f64 in word order (then
//! image order), and ties rank by image index, so scores and rankings are bit-identical in
//! every process and with any thread count.

mod arrays;

pub use arrays::VocabularyArrays;

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

/// How a word's occurrences in one image count towards its weight (before idf and the L1
/// normalization).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TermWeighting {
    /// tf = n (occurrences), DBoW2's.
    Count,
    /// tf = √n: a burst of n descriptors in one word (a repetitive texture: a striped carpet,
    /// tiles) counts √n, not n (Jégou, Douze & Schmid 2009, "On the burstiness of visual
    /// elements").
    Sqrt,
    /// tf = 1 for a word present (n ≥ 1).
    Presence,
}

impl TermWeighting {
    /// tf of a word seen `n` ≥ 1 times.
    fn tf(self, n: usize) -> f64 {
        match self {
            Self::Count => n as f64,
            Self::Sqrt => (n as f64).sqrt(),
            Self::Presence => 1.0,
        }
    }
}

/// One node of the vocabulary tree: the centres of its children and where they lead.
#[derive(Clone, Debug, PartialEq)]
struct Node {
    centres: DescriptorSet,
    /// Per child: another node, or a word (leaf).
    children: Vec<Child>,
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum Child {
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
    nodes: Vec<Node>,
    words: usize,
    binary: bool,
    width: usize,
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

/// TF-IDF image database with an inverted file.
#[derive(Clone, Debug)]
pub struct BowDatabase {
    idf: Vec<f64>,
    weighting: TermWeighting,
    /// word → (image, weight > 0) for the images containing it, by image.
    inverted: Vec<Vec<(u32, f64)>>,
    images: usize,
}

/// L1-normalized TF-IDF vector of one image, sorted by word, zero weights left out:
/// v_w = n_w · idf_w / Σ_u n_u · idf_u (n_w: occurrences of w), summed in f64 in word order.
fn bow_vector(words: &[u32], idf: &[f64], weighting: TermWeighting) -> Vec<(u32, f64)> {
    let mut sorted = words.to_vec();
    sorted.sort_unstable();
    let mut v: Vec<(u32, f64)> = Vec::new();
    for run in sorted.chunk_by(|a, b| a == b) {
        let weight = weighting.tf(run.len()) * idf[run[0] as usize];
        if weight > 0.0 {
            v.push((run[0], weight));
        }
    }
    let norm: f64 = v.iter().map(|(_, x)| x).sum();
    if norm > 0.0 {
        v.iter_mut().for_each(|(_, x)| *x /= norm);
    }
    v
}

impl BowDatabase {
    /// The database of images given as their words (see [`Vocabulary::words_of`]).
    ///
    /// # Errors
    /// A word id beyond the vocabulary (named `images[i]`).
    pub fn new(vocabulary_len: usize, images: &[Vec<u32>]) -> Result<Self> {
        Self::with_weighting(vocabulary_len, images, TermWeighting::Count)
    }

    /// As [`BowDatabase::new`], with the given term weighting (queries use the same).
    ///
    /// # Errors
    /// As [`BowDatabase::new`].
    pub fn with_weighting(vocabulary_len: usize, images: &[Vec<u32>], weighting: TermWeighting) -> Result<Self> {
        let mut containing = vec![0u32; vocabulary_len];
        for (i, words) in images.iter().enumerate() {
            if let Some(&w) = words.iter().find(|&&w| w as usize >= vocabulary_len) {
                return Err(GeolocError::invalid(
                    format!("images[{i}]"),
                    format!("word {w} is not in a vocabulary of {vocabulary_len}"),
                ));
            }
            let mut unique = words.clone();
            unique.sort_unstable();
            unique.dedup();
            for w in unique {
                containing[w as usize] += 1;
            }
        }
        let n = images.len().max(1) as f64;
        let idf: Vec<f64> = containing.iter().map(|&c| if c == 0 { 0.0 } else { (n / f64::from(c)).ln() }).collect();
        let mut inverted = vec![Vec::new(); vocabulary_len];
        for (i, words) in images.iter().enumerate() {
            for (w, weight) in bow_vector(words, &idf, weighting) {
                inverted[w as usize].push((i as u32, weight));
            }
        }
        Ok(Self { idf, weighting, inverted, images: images.len() })
    }

    /// Number of images.
    pub fn len(&self) -> usize {
        self.images
    }

    /// Whether the database holds no images.
    pub fn is_empty(&self) -> bool {
        self.images == 0
    }

    /// The `k` best images for a query's words: (image index, L1 score in [0, 1]), best first.
    /// Scores are summed in f64 in word order, rounded to f32 and clamped to [0, 1]; equal
    /// (rounded) scores rank by image index. Words beyond the vocabulary are ignored.
    pub fn query(&self, words: &[u32], k: usize) -> Vec<(usize, f32)> {
        let known: Vec<u32> = words.iter().copied().filter(|&w| (w as usize) < self.idf.len()).collect();
        let mut scores = vec![0.0f64; self.images];
        for (w, q) in bow_vector(&known, &self.idf, self.weighting) {
            for &(image, v) in &self.inverted[w as usize] {
                // ½(|q| + |v| − |q − v|) = min(q, v) for weights ≥ 0; summed: 1 − ½‖q − v‖₁
                scores[image as usize] += q.min(v);
            }
        }
        let mut ranked: Vec<(usize, f32)> =
            scores.into_iter().map(|s| (s.clamp(0.0, 1.0) as f32).clamp(0.0, 1.0)).enumerate().collect();
        ranked.sort_by(|a, b| b.1.total_cmp(&a.1).then(a.0.cmp(&b.0)));
        ranked.truncate(k);
        ranked
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Images made of a few clusters each; noisy re-draws of an image retrieve it first.
    fn synthetic(binary: bool) {
        let mut rng = SplitMix64::new(7);
        let width = 32;
        let prototypes: Vec<Vec<f32>> =
            (0..60).map(|_| (0..width).map(|_| rng.normal() as f32 * 3.0).collect()).collect();
        let images: Vec<Vec<usize>> = (0..20).map(|i| (0..6).map(|j| (i * 3 + j * 7) % 60).collect()).collect();
        let draw = |rng: &mut SplitMix64, protos: &[usize]| -> Vec<f32> {
            protos
                .iter()
                .flat_map(|&p| {
                    (0..10)
                        .flat_map(|_| prototypes[p].iter().map(|v| v + 0.3 * rng.normal() as f32).collect::<Vec<_>>())
                        .collect::<Vec<_>>()
                })
                .collect()
        };
        let to_bytes = |v: &[f32]| -> Vec<u8> {
            v.chunks(8)
                .map(|c| c.iter().enumerate().fold(0u8, |b, (i, x)| if *x > 0.0 { b | 1 << i } else { b }))
                .collect()
        };
        let train: Vec<Vec<f32>> = images.iter().map(|im| draw(&mut rng, im)).collect();
        let all: Vec<f32> = train.concat();
        let (all_bytes, bw) = (to_bytes(&all), width / 8);
        fn desc<'a>(binary: bool, v: &'a [f32], b: &'a [u8], width: usize, bw: usize) -> Descriptors<'a> {
            if binary { Descriptors::Binary { data: b, width: bw } } else { Descriptors::Float { data: v, width } }
        }
        let vocab = Vocabulary::train(&desc(binary, &all, &all_bytes, width, bw), 8, 2, 1).expect("valid");
        assert!(vocab.len() > 8 && vocab.len() <= 64);
        let words: Vec<Vec<u32>> =
            train.iter().map(|v| vocab.words_of(&desc(binary, v, &to_bytes(v), width, bw)).expect("valid")).collect();
        let db = BowDatabase::new(vocab.len(), &words).expect("valid");
        let mut correct = 0;
        for (i, im) in images.iter().enumerate() {
            let q = draw(&mut rng, im);
            let qw = vocab.words_of(&desc(binary, &q, &to_bytes(&q), width, bw)).expect("valid");
            let best = db.query(&qw, 3);
            correct += usize::from(best[0].0 == i);
            assert!(best[0].1 <= 1.0 + 1e-5 && best.windows(2).all(|w| w[0].1 >= w[1].1));
        }
        assert!(correct >= 18, "{correct}/20 retrieved first");
    }

    #[test]
    fn float_vocabulary_retrieves_the_right_image() {
        synthetic(false);
    }

    #[test]
    fn binary_vocabulary_retrieves_the_right_image() {
        synthetic(true);
    }

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

    /// An image scores exactly 1 against itself (L1 similarity of equal vectors) and ranks
    /// first over a subset of itself.
    #[test]
    fn identical_images_score_one() {
        let mut rng = SplitMix64::new(3);
        let data: Vec<f32> = (0..400 * 8).map(|_| rng.normal() as f32).collect();
        let d = Descriptors::Float { data: &data, width: 8 };
        let vocab = Vocabulary::train(&d, 4, 3, 0).expect("valid");
        let words = vocab.words_of(&d).expect("valid");
        let db = BowDatabase::new(vocab.len(), &[words.clone(), words[..100].to_vec()]).expect("valid");
        let best = db.query(&words, 2);
        assert_eq!(best[0].0, 0);
        assert!((best[0].1 - 1.0).abs() < 1e-5, "{}", best[0].1);
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
        const CHI2_19_999: f64 = 43.82;
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

    /// Scores stay in [0, 1] (summing min(q, v) can round above 1 in f32); an image scores 1
    /// against itself.
    #[test]
    fn scores_stay_in_the_unit_interval() {
        let mut rng = SplitMix64::new(5);
        let images: Vec<Vec<u32>> =
            (0..50).map(|_| (0..300).map(|_| (rng.next_u64() % 997) as u32).collect()).collect();
        let db = BowDatabase::new(997, &images).expect("valid");
        for im in &images {
            for (_, score) in db.query(im, 50) {
                assert!((0.0..=1.0).contains(&score), "{score}");
            }
            assert!((db.query(im, 1)[0].1 - 1.0).abs() < 1e-6);
        }
    }

    /// The same words in another order give bit-identical scores, and identical images (a
    /// stopped camera) tie exactly and rank by index.
    #[test]
    fn scores_do_not_depend_on_word_order_and_ties_rank_by_index() {
        let mut rng = SplitMix64::new(6);
        let base: Vec<u32> = (0..200).map(|_| (rng.next_u64() % 300) as u32).collect();
        let mut images: Vec<Vec<u32>> =
            (0..10).map(|_| (0..200).map(|_| (rng.next_u64() % 300) as u32).collect()).collect();
        images.extend([base.clone(), base.clone(), base.clone()]); // 10, 11, 12 identical
        let db = BowDatabase::new(300, &images).expect("valid");
        let mut reversed = base.clone();
        reversed.reverse();
        let (a, b) = (db.query(&base, 13), db.query(&reversed, 13));
        assert_eq!(
            a.iter().map(|(i, s)| (*i, s.to_bits())).collect::<Vec<_>>(),
            b.iter().map(|(i, s)| (*i, s.to_bits())).collect::<Vec<_>>()
        );
        assert_eq!(a[..3].iter().map(|r| r.0).collect::<Vec<_>>(), vec![10, 11, 12]);
        assert_eq!(a[0].1.to_bits(), a[2].1.to_bits());
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

    /// Scores of every weighting against a dense brute-force TF-IDF (closed form: idf_w =
    /// ln(N / n_w), v = tf·idf / Σ tf·idf, s = Σ_w min(q_w, v_w)), tf = n, √n or [n > 0].
    #[test]
    fn weightings_match_a_dense_reference() {
        let mut rng = SplitMix64::new(11);
        let words = 40;
        // bursty images: a few words repeated many times, as on a striped carpet
        let images: Vec<Vec<u32>> = (0..12)
            .map(|_| {
                let mut w: Vec<u32> = (0..60).map(|_| (rng.next_u64() % words as u64) as u32).collect();
                let burst = (rng.next_u64() % words as u64) as u32;
                w.extend(std::iter::repeat_n(burst, (rng.next_u64() % 30) as usize));
                w
            })
            .collect();
        let query: Vec<u32> = (0..80).map(|_| (rng.next_u64() % (words as u64 + 5)) as u32).collect();
        for (weighting, tf) in [
            (TermWeighting::Count, (|n: f64| n) as fn(f64) -> f64),
            (TermWeighting::Sqrt, |n: f64| n.sqrt()),
            (TermWeighting::Presence, |n: f64| if n > 0.0 { 1.0 } else { 0.0 }),
        ] {
            let db = BowDatabase::with_weighting(words, &images, weighting).expect("valid");
            let counts = |ws: &[u32]| -> Vec<f64> {
                let mut c = vec![0.0; words];
                ws.iter().filter(|&&w| (w as usize) < words).for_each(|&w| c[w as usize] += 1.0);
                c
            };
            let n = images.len() as f64;
            let idf: Vec<f64> = (0..words)
                .map(|w| {
                    let df = images.iter().filter(|im| im.contains(&(w as u32))).count() as f64;
                    if df == 0.0 { 0.0 } else { (n / df).ln() }
                })
                .collect();
            let vector = |ws: &[u32]| -> Vec<f64> {
                let v: Vec<f64> = counts(ws).iter().zip(&idf).map(|(&c, &i)| tf(c) * i).collect();
                let total: f64 = v.iter().sum();
                v.iter().map(|x| x / total).collect()
            };
            let q = vector(&query);
            let got = db.query(&query, images.len());
            for (image, score) in got {
                let want: f64 = vector(&images[image]).iter().zip(&q).map(|(a, b)| a.min(*b)).sum();
                assert!((f64::from(score) - want).abs() < 1e-6, "{weighting:?} image {image}: {score} vs {want}");
            }
        }
        // the weightings differ on these bursty images (the test can tell them apart)
        let score = |w| BowDatabase::with_weighting(words, &images, w).expect("valid").query(&query, 1)[0].1;
        assert!((score(TermWeighting::Count) - score(TermWeighting::Sqrt)).abs() > 1e-3);
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

    /// A burst (one word repeated) dominates the count-weighted score of two otherwise
    /// unrelated images; √n weighting ranks the image that shares the query's distinct
    /// words first.
    #[test]
    fn sqrt_weighting_resists_bursts() {
        // word 0: the burst, in both the query and the decoy; words 1..=10 the query's own
        let mut query: Vec<u32> = vec![0; 40];
        query.extend(1..=10);
        let mut decoy: Vec<u32> = vec![0; 40];
        decoy.extend(20..=29);
        let mut right: Vec<u32> = vec![0; 2];
        right.extend(1..=10);
        let mut others: Vec<Vec<u32>> = (0..6).map(|i| vec![30 + i, 31 + i, 32 + i]).collect();
        others.extend([decoy, right, vec![0, 40, 41]]);
        let best = |w| BowDatabase::with_weighting(50, &others, w).expect("valid").query(&query, 1)[0].0;
        assert_eq!(best(TermWeighting::Count), 6, "count weighting: the decoy wins");
        assert_eq!(best(TermWeighting::Sqrt), 7);
        assert_eq!(best(TermWeighting::Presence), 7);
    }

    #[test]
    fn bad_input() {
        let x = [0u8; 64];
        let d = Descriptors::Binary { data: &x, width: 32 };
        assert!(Vocabulary::train(&d, 4, 2, 0).is_err()); // 2 descriptors, 4 clusters
        assert!(Vocabulary::train(&d, 1, 2, 0).is_err());
        assert!(BowDatabase::new(4, &[vec![5]]).is_err());
        let y = [0.0f32; 64];
        let vocab = Vocabulary::train(&Descriptors::Float { data: &y, width: 8 }, 2, 1, 0).expect("valid");
        assert!(vocab.words_of(&d).is_err());
    }
}
