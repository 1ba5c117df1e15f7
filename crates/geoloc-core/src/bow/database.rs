//! The TF-IDF image database: vectors vᵢ,w = tfᵢ,w · ln(N / n_w) (N images, n_w of them
//! containing w), L1-normalized, in an inverted file; the score of two images is the L1
//! similarity s = 1 − ½‖v − u‖₁ = Σ_w min(v_w, u_w) ∈ [0, 1] (DBoW2's; the weights are ≥ 0),
//! summed over the words they share. The term frequency tf per [`TermWeighting`].

use super::TermWeighting;
use crate::error::{GeolocError, Result};

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
    use crate::rng::SplitMix64;

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
}
