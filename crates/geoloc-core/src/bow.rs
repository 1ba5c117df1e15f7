//! Bag-of-visual-words retrieval (the paper's "BoW + Locator" baseline, and geoloc's default
//! when no descriptor network is given — it needs no training framework).
//!
//! * **Vocabulary**: a tree of `branching`ᵈᵉᵖᵗʰ words built by hierarchical clustering of local
//!   descriptors (Nistér & Stewénius 2006; DBoW2): k-means++ seeding and Lloyd iterations per
//!   node, with Euclidean distance and mean centres for float descriptors (SIFT) and Hamming
//!   distance and bitwise-majority centres (k-majority) for binary ones (ORB). A descriptor's
//!   word is found by descending to the nearest child at each level.
//! * **Database**: TF-IDF vectors vᵢ,w = tfᵢ,w · ln(N / n_w) (N images, n_w of them containing
//!   w), L1-normalized, in an inverted file; the score of two images is the L1 similarity
//!   s = 1 − ½‖v − u‖₁ ∈ [0, 1] (DBoW2's), accumulated over the words they share.

use std::collections::HashMap;

use rayon::prelude::*;

use crate::error::{GeolocError, Result};
use crate::matching::{DescriptorSet, Descriptors};
use crate::testing::SplitMix64;

/// Lloyd iterations per tree node.
const LLOYD_ITERATIONS: usize = 10;

fn distance(desc: &Descriptors<'_>, i: usize, centres: &DescriptorSet, c: usize) -> f32 {
    match (desc, centres) {
        (Descriptors::Binary { data, width }, DescriptorSet::Binary { data: cd, .. }) => {
            crate::matching::hamming(&data[i * width..(i + 1) * width], &cd[c * width..(c + 1) * width]) as f32
        }
        (Descriptors::Float { data, width }, DescriptorSet::Float { data: cd, .. }) => data[i * width..(i + 1) * width]
            .iter()
            .zip(&cd[c * width..(c + 1) * width])
            .map(|(a, b)| (a - b) * (a - b))
            .sum::<f32>(),
        _ => f32::INFINITY,
    }
}

fn count(desc: &Descriptors<'_>) -> usize {
    match *desc {
        Descriptors::Binary { data, width } => data.len() / width.max(1),
        Descriptors::Float { data, width } => data.len() / width.max(1),
    }
}

/// Centre of `members` (k-majority bits or means).
fn centre_of(desc: &Descriptors<'_>, members: &[usize]) -> DescriptorSet {
    match *desc {
        Descriptors::Binary { data, width } => {
            let mut out = vec![0u8; width];
            for byte in 0..width {
                for bit in 0..8 {
                    let ones = members.iter().filter(|&&m| data[m * width + byte] >> bit & 1 == 1).count();
                    if 2 * ones > members.len() {
                        out[byte] |= 1 << bit;
                    }
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

fn concat(parts: Vec<DescriptorSet>) -> DescriptorSet {
    match parts.first() {
        Some(DescriptorSet::Binary { width, .. }) => {
            let width = *width;
            DescriptorSet::Binary {
                data: parts
                    .into_iter()
                    .flat_map(|p| if let DescriptorSet::Binary { data, .. } = p { data } else { Vec::new() })
                    .collect(),
                width,
            }
        }
        Some(DescriptorSet::Float { width, .. }) => {
            let width = *width;
            DescriptorSet::Float {
                data: parts
                    .into_iter()
                    .flat_map(|p| if let DescriptorSet::Float { data, .. } = p { data } else { Vec::new() })
                    .collect(),
                width,
            }
        }
        None => DescriptorSet::Float { data: Vec::new(), width: 0 },
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

/// A hierarchical visual vocabulary.
#[derive(Clone, Debug, PartialEq)]
pub struct Vocabulary {
    nodes: Vec<Node>,
    words: usize,
    binary: bool,
    width: usize,
}

impl Vocabulary {
    /// Clusters `descriptors` into a tree of up to `branching`^`depth` words (seeded).
    ///
    /// # Errors
    /// Fewer descriptors than `branching`, branching < 2, depth 0, a zero width.
    pub fn train(descriptors: &Descriptors<'_>, branching: usize, depth: usize, seed: u64) -> Result<Self> {
        let (binary, width) = match *descriptors {
            Descriptors::Binary { width, .. } => (true, width),
            Descriptors::Float { width, .. } => (false, width),
        };
        if width == 0 {
            return Err(GeolocError::invalid("descriptors", "zero-width descriptors"));
        }
        if branching < 2 || depth == 0 {
            return Err(GeolocError::invalid(
                "branching",
                format!("need branching ≥ 2 and depth ≥ 1, got {branching}, {depth}"),
            ));
        }
        let n = count(descriptors);
        if n < branching {
            return Err(GeolocError::invalid(
                "descriptors",
                format!("{n} descriptors cannot make {branching} clusters"),
            ));
        }
        let mut vocabulary = Self { nodes: Vec::new(), words: 0, binary, width };
        let mut rng = SplitMix64::new(seed);
        let all: Vec<usize> = (0..n).collect();
        vocabulary.build(descriptors, &all, branching, depth, &mut rng);
        Ok(vocabulary)
    }

    /// Builds the node for `members`; returns its index.
    fn build(
        &mut self,
        desc: &Descriptors<'_>,
        members: &[usize],
        branching: usize,
        depth: usize,
        rng: &mut SplitMix64,
    ) -> usize {
        let k = branching.min(members.len());
        let (centres, clusters) = kmeans(desc, members, k, rng);
        let index = self.nodes.len();
        self.nodes.push(Node { centres, children: Vec::new() });
        let mut children = Vec::with_capacity(k);
        for cluster in clusters {
            if depth > 1 && cluster.len() > branching {
                let child = self.build(desc, &cluster, branching, depth - 1, rng);
                children.push(Child::Node(child));
            } else {
                children.push(Child::Word(self.words as u32));
                self.words += 1;
            }
        }
        self.nodes[index].children = children;
        index
    }

    /// Number of words (leaves).
    pub fn len(&self) -> usize {
        self.words
    }

    /// Whether the vocabulary has no words (never after training).
    pub fn is_empty(&self) -> bool {
        self.words == 0
    }

    /// The word of each descriptor (descending to the nearest child at each level).
    ///
    /// # Errors
    /// Descriptors of the other kind or width than the vocabulary's.
    pub fn words_of(&self, descriptors: &Descriptors<'_>) -> Result<Vec<u32>> {
        let (binary, width) = match *descriptors {
            Descriptors::Binary { width, .. } => (true, width),
            Descriptors::Float { width, .. } => (false, width),
        };
        if binary != self.binary || width != self.width {
            return Err(GeolocError::invalid(
                "descriptors",
                format!(
                    "the vocabulary is for {} descriptors of width {}",
                    if self.binary { "binary" } else { "float" },
                    self.width
                ),
            ));
        }
        Ok((0..count(descriptors))
            .into_par_iter()
            .map(|i| {
                let mut node = 0;
                loop {
                    let n = &self.nodes[node];
                    let best = (0..n.children.len())
                        .min_by(|&a, &b| {
                            distance(descriptors, i, &n.centres, a).total_cmp(&distance(descriptors, i, &n.centres, b))
                        })
                        .expect("invariant: nodes have children");
                    match n.children[best] {
                        Child::Node(next) => node = next,
                        Child::Word(w) => return w,
                    }
                }
            })
            .collect())
    }
}

/// k-means++ seeding then Lloyd iterations over `members`; returns centres and clusters.
fn kmeans(
    desc: &Descriptors<'_>,
    members: &[usize],
    k: usize,
    rng: &mut SplitMix64,
) -> (DescriptorSet, Vec<Vec<usize>>) {
    // k-means++: first centre uniform, then proportional to the squared distance
    let mut seeds = vec![members[(rng.next_u64() % members.len() as u64) as usize]];
    let mut nearest: Vec<f32> = vec![f32::INFINITY; members.len()];
    while seeds.len() < k {
        let last = centre_of(desc, &[*seeds.last().expect("invariant: one seed")]);
        let mut total = 0.0f64;
        for (slot, &m) in nearest.iter_mut().zip(members) {
            *slot = slot.min(distance(desc, m, &last, 0));
            total += f64::from(*slot) * f64::from(*slot);
        }
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
    let mut centres = concat(seeds.iter().map(|&s| centre_of(desc, &[s])).collect());
    let mut clusters = vec![Vec::new(); k];
    for _ in 0..LLOYD_ITERATIONS {
        clusters = vec![Vec::new(); k];
        for &m in members {
            let best = (0..k)
                .min_by(|&a, &b| distance(desc, m, &centres, a).total_cmp(&distance(desc, m, &centres, b)))
                .expect("k ≥ 1");
            clusters[best].push(m);
        }
        let next = concat(
            clusters
                .iter()
                .enumerate()
                .map(
                    |(c, members)| {
                        if members.is_empty() { centre_of(desc, &[seeds[c]]) } else { centre_of(desc, members) }
                    },
                )
                .collect(),
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
    idf: Vec<f32>,
    /// word → (image, weight) for the images containing it.
    inverted: Vec<Vec<(u32, f32)>>,
    images: usize,
}

/// L1-normalized TF-IDF vector of one image (sparse: word → weight).
fn bow_vector(words: &[u32], idf: &[f32]) -> HashMap<u32, f32> {
    let mut v: HashMap<u32, f32> = HashMap::new();
    for &w in words {
        *v.entry(w).or_insert(0.0) += idf[w as usize];
    }
    let norm: f32 = v.values().map(|x| x.abs()).sum();
    if norm > 0.0 {
        v.values_mut().for_each(|x| *x /= norm);
    }
    v
}

impl BowDatabase {
    /// The database of images given as their words (see [`Vocabulary::words_of`]).
    ///
    /// # Errors
    /// A word id beyond the vocabulary.
    pub fn new(vocabulary_len: usize, images: &[Vec<u32>]) -> Result<Self> {
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
        let n = images.len().max(1) as f32;
        let idf: Vec<f32> = containing.iter().map(|&c| if c == 0 { 0.0 } else { (n / c as f32).ln() }).collect();
        let mut inverted = vec![Vec::new(); vocabulary_len];
        for (i, words) in images.iter().enumerate() {
            for (w, weight) in bow_vector(words, &idf) {
                inverted[w as usize].push((i as u32, weight));
            }
        }
        Ok(Self { idf, inverted, images: images.len() })
    }

    /// The `k` best images for a query's words: (image index, L1 score), best first, ties by
    /// index.
    pub fn query(&self, words: &[u32], k: usize) -> Vec<(usize, f32)> {
        let q = bow_vector(
            &words.iter().copied().filter(|&w| (w as usize) < self.idf.len()).collect::<Vec<_>>(),
            &self.idf,
        );
        let mut scores = vec![0.0f32; self.images];
        for (&w, &qv) in &q {
            for &(image, v) in &self.inverted[w as usize] {
                // ½(|q| + |v| − |q − v|) summed over shared words = 1 − ½‖q − v‖₁
                scores[image as usize] += 0.5 * (qv.abs() + v.abs() - (qv - v).abs());
            }
        }
        let mut ranked: Vec<(usize, f32)> = scores.into_iter().enumerate().collect();
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
