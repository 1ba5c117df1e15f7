//! The map a camera is localized against: keyframes with known world_from_cam poses, their
//! keypoints (undistorted pixels) and local descriptors, optional global descriptors, the
//! camera, and the retrieval structure built from them (a descriptor index when a network
//! provides global descriptors, else a bag-of-words vocabulary and database).

pub mod file;

use nalgebra::{Matrix6, Vector2};

use crate::bow::{BowDatabase, Vocabulary};
use crate::camera::Camera;
use crate::error::{GeolocError, Result};
use crate::lie::SE3;
pub use crate::matching::DescriptorSet;
use crate::matching::Descriptors;
use crate::retrieval::DescriptorIndex;

/// One keyframe of the map.
#[derive(Clone, Debug, PartialEq)]
pub struct Keyframe {
    /// Pose label (world_from_cam).
    pub world_from_cam: SE3,
    /// Keypoints, undistorted pixels.
    pub keypoints: Vec<Vector2<f64>>,
    /// One local descriptor per keypoint.
    pub descriptors: DescriptorSet,
    /// Global descriptor from a network, if any.
    pub global: Option<Vec<f32>>,
}

/// How the map retrieves the keyframe most similar to a query image.
pub enum Retrieval {
    /// Nearest global descriptor.
    Global(DescriptorIndex),
    /// Bag of words over the local descriptors.
    Bow {
        /// The vocabulary.
        vocabulary: Vocabulary,
        /// The keyframes' TF-IDF database.
        database: BowDatabase,
    },
}

/// The map.
pub struct Map {
    /// Intrinsics shared by keyframes and queries.
    pub camera: Camera,
    /// The keyframes, in capture order.
    pub keyframes: Vec<Keyframe>,
    /// Covariances of the pose labels (right perturbation), if known.
    pub pose_covariances: Option<Vec<Matrix6<f64>>>,
    /// The retrieval structure.
    pub retrieval: Retrieval,
}

/// How to build the retrieval structure.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum RetrievalKind {
    /// Use the keyframes' global descriptors (all must have one, of equal length).
    Global,
    /// Train a BoW vocabulary of `branching`^`depth` words on the keyframes' descriptors.
    Bow {
        /// Children per node.
        branching: usize,
        /// Levels.
        depth: usize,
    },
}

impl Map {
    /// Builds the map and its retrieval structure.
    ///
    /// # Errors
    /// No keyframes, keypoint/descriptor counts that disagree, mixed descriptor kinds or
    /// widths, missing or unequal global descriptors for `Global`, bad covariances count.
    pub fn build(
        camera: Camera,
        keyframes: Vec<Keyframe>,
        pose_covariances: Option<Vec<Matrix6<f64>>>,
        kind: RetrievalKind,
        seed: u64,
    ) -> Result<Self> {
        if keyframes.is_empty() {
            return Err(GeolocError::invalid("keyframes", "the map needs at least one keyframe"));
        }
        if let Some(c) = &pose_covariances
            && c.len() != keyframes.len()
        {
            return Err(GeolocError::invalid(
                "pose_covariances",
                format!("has {} entries for {} keyframes", c.len(), keyframes.len()),
            ));
        }
        let kind_of = |d: &DescriptorSet| match d {
            DescriptorSet::Binary { width, .. } => (true, *width),
            DescriptorSet::Float { width, .. } => (false, *width),
        };
        let first = kind_of(&keyframes[0].descriptors);
        for (i, kf) in keyframes.iter().enumerate() {
            if kf.keypoints.len() != kf.descriptors.len() {
                return Err(GeolocError::invalid(
                    format!("keyframes[{i}]"),
                    format!("{} keypoints but {} descriptors", kf.keypoints.len(), kf.descriptors.len()),
                ));
            }
            if kind_of(&kf.descriptors) != first {
                return Err(GeolocError::invalid(
                    format!("keyframes[{i}]"),
                    "descriptors differ in kind or width from keyframe 0's",
                ));
            }
        }
        let retrieval = match kind {
            RetrievalKind::Global => {
                let dim = keyframes[0].global.as_ref().map_or(0, Vec::len);
                let mut data = Vec::with_capacity(dim * keyframes.len());
                for (i, kf) in keyframes.iter().enumerate() {
                    match &kf.global {
                        Some(g) if g.len() == dim && dim > 0 => data.extend_from_slice(g),
                        _ => {
                            return Err(GeolocError::invalid(
                                format!("keyframes[{i}]"),
                                format!("needs a global descriptor of length {dim}"),
                            ));
                        }
                    }
                }
                Retrieval::Global(DescriptorIndex::new(data, dim)?)
            }
            RetrievalKind::Bow { branching, depth } => {
                let all = match &keyframes[0].descriptors {
                    DescriptorSet::Binary { width, .. } => DescriptorSet::Binary {
                        data: keyframes
                            .iter()
                            .flat_map(|k| {
                                if let DescriptorSet::Binary { data, .. } = &k.descriptors {
                                    data.clone()
                                } else {
                                    Vec::new()
                                }
                            })
                            .collect(),
                        width: *width,
                    },
                    DescriptorSet::Float { width, .. } => DescriptorSet::Float {
                        data: keyframes
                            .iter()
                            .flat_map(|k| {
                                if let DescriptorSet::Float { data, .. } = &k.descriptors {
                                    data.clone()
                                } else {
                                    Vec::new()
                                }
                            })
                            .collect(),
                        width: *width,
                    },
                };
                let vocabulary = Vocabulary::train(&all.view(), branching, depth, seed)?;
                let words: Vec<Vec<u32>> =
                    keyframes.iter().map(|k| vocabulary.words_of(&k.descriptors.view())).collect::<Result<_>>()?;
                let database = BowDatabase::new(vocabulary.len(), &words)?;
                Retrieval::Bow { vocabulary, database }
            }
        };
        Ok(Self { camera, keyframes, pose_covariances, retrieval })
    }

    /// The world_from_cam poses of the keyframes.
    pub fn poses(&self) -> Vec<SE3> {
        self.keyframes.iter().map(|k| k.world_from_cam).collect()
    }

    /// The keyframe most similar to a query (by its global descriptor, or by its local
    /// descriptors through BoW).
    ///
    /// # Errors
    /// A query without what the map's retrieval needs, or of the wrong size.
    pub fn retrieve(&self, descriptors: &Descriptors<'_>, global: Option<&[f32]>) -> Result<usize> {
        match &self.retrieval {
            Retrieval::Global(index) => {
                let g = global.ok_or_else(|| {
                    GeolocError::invalid("global", "this map retrieves by global descriptor; give one")
                })?;
                let (_, idx) = index.query(g, 1)?;
                Ok(idx[0])
            }
            Retrieval::Bow { vocabulary, database } => {
                let words = vocabulary.words_of(descriptors)?;
                database
                    .query(&words, 1)
                    .first()
                    .map(|&(i, _)| i)
                    .ok_or_else(|| GeolocError::invalid("descriptors", "the map has no keyframes"))
            }
        }
    }
}
