//! Bag-of-visual-words retrieval (the paper's "BoW + Locator" baseline, and geoloc's default
//! when no descriptor network is given — it needs no training framework): a descriptor's
//! visual word from the vocabulary tree ([`Vocabulary`], the `vocabulary` submodule), and the
//! images most similar to a query's words by TF-IDF scoring ([`BowDatabase`], the `database`
//! submodule).
//!
//! **Term weighting per descriptor kind** ([`Vocabulary::term_weighting`], used by the map,
//! its file and the Python `BowDatabase`): tf = the count n for binary descriptors (ORB,
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
mod database;
mod vocabulary;

pub use arrays::VocabularyArrays;
pub use database::BowDatabase;
pub use vocabulary::{MAX_BRANCHING, MAX_DEPTH, MAX_WORDS, Vocabulary};

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

#[cfg(test)]
mod tests {
    use super::{BowDatabase, Vocabulary};
    use crate::matching::Descriptors;
    use crate::rng::SplitMix64;

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
