//! The vocabulary tree as flat arrays, for storing it in a map file and reading it back.
//!
//! Nodes are numbered in the order training creates them (depth first), so every child node
//! has a larger index than its parent. Node `i`'s children are rows
//! `node_offsets[i]..node_offsets[i + 1]` of `centres` and `children`; `children[r] ≥ 0` is the
//! index of a child node, `children[r] < 0` the word `−children[r] − 1`.
//!
//! A stored tree is held to the shape training can give it: every node but the root has one
//! parent, a node has at most [`MAX_BRANCHING`] children, words lie at most [`MAX_DEPTH`]
//! levels down, and bᵈ ≤ [`MAX_WORDS`] for the widest node's b children and the depth d. So
//! finding a descriptor's word costs at most b·d ≤ 2048 distances (b = 1024, d = 2), whatever
//! the file says; a crafted chain of 200 000 nodes (one descent of 200 000 distances per
//! descriptor) is refused in one pass over the offsets, before any node is built.

use super::vocabulary::{Child, MAX_BRANCHING, MAX_DEPTH, MAX_WORDS, Node, Vocabulary};
use crate::error::{GeolocError, Result};
use crate::matching::DescriptorSet;

/// A [`Vocabulary`] as flat arrays; see the module doc.
#[derive(Clone, Debug, PartialEq)]
pub struct VocabularyArrays {
    /// Row offsets of each node's children (length nodes + 1).
    pub node_offsets: Vec<i64>,
    /// The children's centres, one row each (binary or float, as the vocabulary's descriptors).
    pub centres: DescriptorSet,
    /// Per row: a child node index (≥ 0) or a word as −word − 1.
    pub children: Vec<i64>,
}

fn malformed(reason: impl Into<String>) -> GeolocError {
    GeolocError::invalid("vocabulary", reason)
}

impl Vocabulary {
    /// The tree as flat arrays.
    pub fn to_arrays(&self) -> VocabularyArrays {
        let mut node_offsets = vec![0i64];
        let mut children = Vec::new();
        for node in &self.nodes {
            children.extend(node.children.iter().map(|c| match *c {
                Child::Node(i) => i as i64,
                Child::Word(w) => -i64::from(w) - 1,
            }));
            node_offsets.push(children.len() as i64);
        }
        let centres = DescriptorSet::stack(self.nodes.iter().map(|n| &n.centres));
        VocabularyArrays { node_offsets, centres, children }
    }

    /// The vocabulary from flat arrays, checked so that every descent ends at a word: offsets
    /// partition the rows, every node has a child, child nodes have larger indices than their
    /// parent, and the words are exactly 0..W, each once; and held to the shape training gives
    /// (see the module doc): one parent per node, at most [`MAX_BRANCHING`] children, at most
    /// [`MAX_DEPTH`] levels, bᵈ ≤ [`MAX_WORDS`].
    ///
    /// # Errors
    /// `InvalidInput` named `vocabulary` saying which check failed, naming the limit exceeded.
    pub fn from_arrays(arrays: VocabularyArrays) -> Result<Self> {
        let VocabularyArrays { node_offsets, centres, children } = arrays;
        let n_nodes = node_offsets.len().checked_sub(1).filter(|&n| n > 0).ok_or_else(|| malformed("no nodes"))?;
        if node_offsets[0] != 0
            || node_offsets.windows(2).any(|w| w[1] <= w[0])
            || node_offsets[n_nodes] != children.len() as i64
            || centres.len() != children.len()
        {
            return Err(malformed("node offsets do not partition the children"));
        }
        check_shape(&node_offsets, &children)?;
        let mut word_seen = vec![false; children.iter().filter(|&&c| c < 0).count()];
        let (binary, width) = match &centres {
            DescriptorSet::Binary { width, .. } => (true, *width),
            DescriptorSet::Float { width, data } => {
                if data.iter().any(|v| !v.is_finite()) {
                    return Err(malformed("centres hold non-finite values"));
                }
                (false, *width)
            }
        };
        let mut nodes = Vec::with_capacity(n_nodes);
        for i in 0..n_nodes {
            let (a, b) = (node_offsets[i] as usize, node_offsets[i + 1] as usize);
            let mut node_children = Vec::with_capacity(b - a);
            for &c in &children[a..b] {
                node_children.push(if c >= 0 {
                    let child = usize::try_from(c).unwrap_or(usize::MAX);
                    if child <= i || child >= n_nodes {
                        return Err(malformed(format!("node {i} has child node {c}, not in {}..{n_nodes}", i + 1)));
                    }
                    Child::Node(child)
                } else {
                    let w = usize::try_from(-(c + 1)).unwrap_or(usize::MAX);
                    match word_seen.get_mut(w) {
                        Some(seen) if !*seen => *seen = true,
                        _ => return Err(malformed(format!("word {w} is out of range or repeated"))),
                    }
                    Child::Word(w as u32)
                });
            }
            let rows: Vec<usize> = (a..b).collect();
            nodes.push(Node { centres: centres.select(&rows), children: node_children });
        }
        Ok(Self { nodes, words: word_seen.len(), binary, width })
    }
}

/// The checks of the tree's shape (module doc), in one pass in node order (a child node has a
/// larger index than its parent, so its parent's level is known when it is reached). Runs
/// after the offsets are known to partition the children.
fn check_shape(node_offsets: &[i64], children: &[i64]) -> Result<()> {
    let n_nodes = node_offsets.len() - 1;
    // the level of each node's children (the root's are at level 1); 0 = no parent seen yet
    let mut level = vec![0usize; n_nodes];
    level[0] = 1;
    let (mut widest, mut deepest) = (0usize, 0usize);
    for i in 0..n_nodes {
        let (a, b) = (node_offsets[i] as usize, node_offsets[i + 1] as usize);
        if b - a > MAX_BRANCHING {
            return Err(malformed(format!(
                "node {i} has {} children, more than the limit of {MAX_BRANCHING} (MAX_BRANCHING)",
                b - a
            )));
        }
        if i > 0 && level[i] == 0 {
            return Err(malformed(format!("node {i} has no parent")));
        }
        if level[i] > MAX_DEPTH {
            return Err(malformed(format!(
                "node {i}'s children are at level {}, deeper than the limit of {MAX_DEPTH} levels (MAX_DEPTH)",
                level[i]
            )));
        }
        widest = widest.max(b - a);
        deepest = deepest.max(level[i]);
        for &c in &children[a..b] {
            let Ok(child) = usize::try_from(c) else { continue }; // a word
            if child <= i || child >= n_nodes {
                return Err(malformed(format!("node {i} has child node {c}, not in {}..{n_nodes}", i + 1)));
            }
            if level[child] != 0 {
                return Err(malformed(format!("node {child} has two parents")));
            }
            level[child] = level[i] + 1;
        }
    }
    let words = u32::try_from(deepest).ok().and_then(|d| widest.checked_pow(d));
    if words.is_none_or(|w| w > MAX_WORDS) {
        return Err(malformed(format!(
            "{widest} children per node over {deepest} levels (up to {widest}^{deepest} words) exceed the \
             limit of {MAX_WORDS} words (MAX_WORDS)"
        )));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::SplitMix64;

    fn trained(binary: bool) -> (Vocabulary, DescriptorSet) {
        let mut rng = SplitMix64::new(9);
        let set = if binary {
            DescriptorSet::Binary { data: (0..400 * 32).map(|_| (rng.next_u64() & 0xff) as u8).collect(), width: 32 }
        } else {
            DescriptorSet::Float {
                data: (0..400 * 8).map(|_| rng.next_u64() as f32 / u64::MAX as f32).collect(),
                width: 8,
            }
        };
        (Vocabulary::train(&set.view(), 4, 3, 1).expect("trains"), set)
    }

    #[test]
    fn round_trip_gives_the_same_vocabulary_and_words() {
        for binary in [true, false] {
            let (vocabulary, set) = trained(binary);
            let back = Vocabulary::from_arrays(vocabulary.to_arrays()).expect("valid arrays");
            assert_eq!(back, vocabulary);
            assert_eq!(back.words_of(&set.view()).expect("words"), vocabulary.words_of(&set.view()).expect("words"));
        }
    }

    #[test]
    fn malformed_trees_are_refused() {
        let (vocabulary, _) = trained(true);
        let good = vocabulary.to_arrays();
        let first_node_child = good.children.iter().position(|&c| c > 0).expect("a child node");
        let mut cycle = good.clone();
        cycle.children[first_node_child] = 0; // points back at the root
        let mut repeated = good.clone();
        let words: Vec<usize> = (0..good.children.len()).filter(|&r| good.children[r] < 0).take(2).collect();
        repeated.children[words[1]] = repeated.children[words[0]];
        let mut offsets = good.clone();
        offsets.node_offsets[1] = offsets.node_offsets[2] + 1;
        for (what, bad) in [("cycle", cycle), ("repeated word", repeated), ("offsets", offsets)] {
            let err = Vocabulary::from_arrays(bad).expect_err(what);
            assert!(
                matches!(err, GeolocError::InvalidInput { ref name, .. } if name == "vocabulary"),
                "{what}: {err:?}"
            );
        }
    }
}
