//! The per-frame localizer: the paper's pipeline frame after frame.
//!
//! retrieval (global index or BoW) → keyframe group around the retrieved keyframe → matches
//! from the seed keyframe to the rest of the group, epipolar-checked with their known poses →
//! tracks → triangulation (cached per group) → query-to-map matching → PnP with the points'
//! uncertainty (T_G, C_G) → constant-velocity prediction from the last fused poses (T_M, C_M)
//! → gated fusion (T_F, C_F). The first frames, before there is any history, use the
//! geometric pose alone. In sequence, a frame whose retrieved group gives fewer than half
//! the last frame's inliers is also tried against the last frame's group (tracking; the
//! paper's locator). Every result says which path produced it and why.
//!
//! This module is the state machine: the options, the per-frame result and the history,
//! prediction, gate and fusion (steps (d) and (e)).
//! `LocalizerOptions::locator` picks the geometric locator: [`Locator::Paper`] (the above,
//! steps (a)–(c); the `paper` submodule) or [`Locator::Model`] (top-k retrieval against the map-level 3D model,
//! PnP on the union, guided matching; see the `model` submodule). (d) and (e) are shared.

use std::collections::{HashMap, VecDeque};
use std::sync::Arc;
use std::time::Instant;

use nalgebra::{Matrix6, Vector2};

use crate::error::{GeolocError, Result};
use crate::fusion::{FusionSource, Gate, fuse_gated_with};
use crate::keyframes::KeyframeOptions;
use crate::lie::SE3;
use crate::map::group_matches::fingerprint;
use crate::map::{Map, ModelOptions, Ranking, Retrieval, RetrievalQuery, SceneModel};
use crate::matching::{Descriptors, MatchOptions};
use crate::motion::{motion_predict_with_noise, motion_predict_with_prior};
use crate::optim::covariance::{isometric_sigmas, spd_inverse};

mod acceptance;
mod grid;
mod holdout;
mod model;
mod paper;
pub use crate::map::noise::{
    DEFAULT_MAP_SIGMA_DEG, DEFAULT_MAP_SIGMA_M, MIN_NOISE_SAMPLES, NoiseOptions, default_map_covariance,
};
use crate::pnp::PnpOptions;
use crate::stats::chi2::chi2_6_quantile_for_sigma;
use crate::triangulate::TriangulationOptions;
pub use acceptance::{AcceptanceOptions, rejection as acceptance_rejection, viewpoint_consistent};
use paper::MapPoints;

/// Options of the [`Localizer`], defaults from the paper.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LocalizerOptions {
    /// Keyframe group selection.
    pub keyframes: KeyframeOptions,
    /// Local-descriptor matching (keyframe–keyframe and query–map).
    pub matching: MatchOptions,
    /// Sampson threshold of the keyframe–keyframe epipolar check (default 2 px).
    pub epipolar_px: f64,
    /// Forward intersection.
    pub triangulation: TriangulationOptions,
    /// Backward intersection.
    pub pnp: PnpOptions,
    /// t: fused poses the motion model is fitted to (default 4).
    pub history: usize,
    /// Gate of the geometric pose against the prediction, in σ (default 3).
    pub gate_sigma: f64,
    /// Which gate (default the paper's isometric one).
    pub gate: Gate,
    /// Fewest 2D–3D correspondences worth a PnP (default 12).
    pub min_correspondences: usize,
    /// N: this many consecutive geometric poses that agree with each other but not with
    /// the prediction re-initialize the motion history from them (default 3, ≥ 3).
    pub reinit_after: usize,
    /// M: after this many consecutive motion-only frames the frame is reported lost and
    /// the motion history cleared (default 10).
    pub lost_after: usize,
    /// ... or as soon as the prediction's isometric position σ exceeds this (m, default 0.25).
    pub max_motion_sigma_m: f64,
    /// Which geometric locator (default the model locator: on every 7-Scenes fold it is
    /// closer to the image-consistent reference and loses fewer frames than the paper's).
    pub locator: Locator,
    /// Model locator: keyframes retrieved and solved from together (default 5; the next
    /// `top_k` of the ranking when those give no accepted pose).
    pub top_k: usize,
    /// Model locator: radius of the guided matching around each projected point (px, default 6).
    pub guided_radius_px: f64,
    /// Model locator: rounds of guided matching and refinement (default 2; 0 = none).
    pub guided_rounds: usize,
    /// Model locator: how the 3D model is built when the map has none.
    pub model: ModelOptions,
    /// When a geometric pose may be reported (both locators; see [`AcceptanceOptions`]).
    pub acceptance: AcceptanceOptions,
}

/// Which geometric locator a [`Localizer`] uses.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Locator {
    /// The paper's: one retrieved keyframe, its co-visible group, points triangulated on the fly.
    Paper,
    /// The map-level 3D model: top-k retrieval, 2D–3D matching, PnP, guided matching.
    Model,
}

impl Locator {
    /// Every locator, in declaration order.
    pub const ALL: [Self; 2] = [Self::Paper, Self::Model];

    /// The name: `"paper"` or `"model"` (the one place that spells it).
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Paper => "paper",
            Self::Model => "model",
        }
    }
}

impl std::fmt::Display for Locator {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

impl std::str::FromStr for Locator {
    type Err = GeolocError;

    fn from_str(s: &str) -> Result<Self> {
        Self::ALL
            .into_iter()
            .find(|v| v.as_str() == s)
            .ok_or_else(|| GeolocError::invalid("locator", format!("expected \"paper\" or \"model\", got {s:?}")))
    }
}

impl Default for LocalizerOptions {
    fn default() -> Self {
        Self {
            keyframes: KeyframeOptions::default(),
            matching: MatchOptions::default(),
            epipolar_px: 2.0,
            triangulation: TriangulationOptions::default(),
            pnp: PnpOptions::default(),
            history: 4,
            gate_sigma: 3.0,
            gate: Gate::Isometric,
            min_correspondences: 12,
            reinit_after: 3,
            lost_after: 10,
            max_motion_sigma_m: 0.25,
            locator: Locator::Model,
            top_k: 5,
            guided_radius_px: 6.0,
            guided_rounds: 2,
            model: ModelOptions::default(),
            acceptance: AcceptanceOptions::default(),
        }
    }
}

impl LocalizerOptions {
    /// A keypoint's positional σ (px) for PnP and triangulation alike (one value: see
    /// [`LocalizerOptions::with_pixel_noise`]).
    pub fn pixel_sigma(&self) -> f64 {
        self.pnp.pixel_sigma
    }

    /// The largest reprojection residual kept (px), in PnP and triangulation alike.
    pub fn max_residual_px(&self) -> f64 {
        self.pnp.max_residual_px
    }

    /// These options with one pixel-noise model for the query and the map: `pixel_sigma`
    /// (px, a keypoint's positional 1σ, scaled per keypoint by its detector σ) and
    /// `max_residual_px` set in both PnP and triangulation, so that the points' covariance
    /// and the pose's covariance assume the same noise.
    #[must_use]
    pub fn with_pixel_noise(mut self, pixel_sigma: f64, max_residual_px: f64) -> Self {
        self.pnp.pixel_sigma = pixel_sigma;
        self.pnp.max_residual_px = max_residual_px;
        self.triangulation.pixel_sigma = pixel_sigma;
        self.triangulation.max_residual_px = max_residual_px;
        self
    }

    /// Checks the options the localizer itself uses (the solvers check theirs again).
    ///
    /// # Errors
    /// See [`Localizer::new`].
    pub fn check(&self) -> Result<()> {
        if self.history < 2 {
            return Err(GeolocError::invalid("history", format!("must be ≥ 2, got {}", self.history)));
        }
        if self.reinit_after < 3 {
            return Err(GeolocError::invalid("reinit_after", format!("must be ≥ 3, got {}", self.reinit_after)));
        }
        if self.top_k == 0 {
            return Err(GeolocError::invalid("top_k", "must be ≥ 1"));
        }
        self.model.check()?;
        self.acceptance.check()?;
        let positive = [
            ("guided_radius", self.guided_radius_px),
            ("gate_sigma", self.gate_sigma),
            ("epipolar_px", self.epipolar_px),
            ("max_motion_sigma_m", self.max_motion_sigma_m),
            ("pixel_sigma", self.pnp.pixel_sigma),
            ("pixel_sigma", self.triangulation.pixel_sigma),
            ("max_residual", self.pnp.max_residual_px),
            ("max_residual", self.triangulation.max_residual_px),
        ];
        match positive.into_iter().find(|(_, v)| !(v.is_finite() && *v > 0.0)) {
            Some((name, v)) => Err(GeolocError::invalid(name, format!("must be finite and > 0, got {v}"))),
            None => Ok(()),
        }
    }
}

/// One query frame: its features, from the caller's detector.
#[derive(Clone, Copy, Debug)]
pub struct Frame<'a> {
    /// Capture time (seconds, increasing).
    pub timestamp: f64,
    /// Keypoints, undistorted pixels.
    pub keypoints: &'a [Vector2<f64>],
    /// One local descriptor per keypoint.
    pub descriptors: Descriptors<'a>,
    /// Global descriptor, when the map retrieves by one.
    pub global: Option<&'a [f32]>,
    /// Each keypoint's positional σ from its detector scale (px; e.g. 1.2^level for ORB,
    /// [`crate::frames::FrameRecord::pixel_sigmas`]): keypoint i's pixel noise in PnP is
    /// `pnp.pixel_sigma` × `pixel_sigmas[i]`. None: `pnp.pixel_sigma` for every keypoint.
    pub pixel_sigmas: Option<&'a [f64]>,
}

impl<'a> Frame<'a> {
    /// What the map's retrieval compares: keypoints, local and global descriptors.
    pub fn retrieval_query(&self) -> RetrievalQuery<'a> {
        RetrievalQuery { keypoints: self.keypoints, descriptors: self.descriptors, global: self.global }
    }
}

/// Which path produced a result.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Source {
    /// The geometric locator alone (no motion history yet).
    Geometric,
    /// Geometric and motion poses fused.
    Fused,
    /// The motion prediction (the geometric pose failed or was gated).
    Motion,
    /// Neither.
    Lost,
}

impl Source {
    /// Every source, in declaration order.
    pub const ALL: [Self; 4] = [Self::Geometric, Self::Fused, Self::Motion, Self::Lost];

    /// The name: `"geometric"`, `"fused"`, `"motion"` or `"lost"` (the one place that spells it).
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Geometric => "geometric",
            Self::Fused => "fused",
            Self::Motion => "motion",
            Self::Lost => "lost",
        }
    }
}

impl std::fmt::Display for Source {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

impl std::str::FromStr for Source {
    type Err = GeolocError;

    fn from_str(s: &str) -> Result<Self> {
        Self::ALL.into_iter().find(|v| v.as_str() == s).ok_or_else(|| {
            GeolocError::invalid(
                "source",
                format!("expected \"geometric\", \"fused\", \"motion\" or \"lost\", got {s:?}"),
            )
        })
    }
}

/// A pose with its covariance.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Estimate {
    /// world_from_cam.
    pub world_from_cam: SE3,
    /// 6×6 covariance, right perturbation, translation first.
    pub covariance: Matrix6<f64>,
    /// The part of `covariance` independent from one frame to the next (a geometric pose's
    /// pixel noise, [`crate::pnp::PnpResult::pixel_covariance`]): what the motion history
    /// and the fusion weigh by. The rest — the map points' and keyframes' errors — is shared
    /// by consecutive frames that see the same points and is not averaged down.
    pub pixel_covariance: Matrix6<f64>,
}

/// Milliseconds spent in each stage.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Timings {
    /// Retrieval of the most similar keyframe.
    pub retrieval_ms: f64,
    /// Keyframe group selection.
    pub keyframes_ms: f64,
    /// Keyframe matching and triangulation (0 when the group was cached).
    pub map_points_ms: f64,
    /// Query-to-map matching.
    pub matching_ms: f64,
    /// PnP.
    pub pnp_ms: f64,
    /// Motion model and fusion.
    pub motion_fusion_ms: f64,
    /// Everything.
    pub total_ms: f64,
}

impl Timings {
    /// The stage names, in pipeline order, as every front end reports them.
    pub const STAGES: [&'static str; 7] =
        ["retrieval", "keyframes", "map_points", "matching", "pnp", "motion_fusion", "total"];

    /// (stage name, milliseconds) in the order of [`Timings::STAGES`].
    pub fn stages(&self) -> [(&'static str, f64); 7] {
        let ms = [
            self.retrieval_ms,
            self.keyframes_ms,
            self.map_points_ms,
            self.matching_ms,
            self.pnp_ms,
            self.motion_fusion_ms,
            self.total_ms,
        ];
        std::array::from_fn(|i| (Self::STAGES[i], ms[i]))
    }
}

/// The localization of one frame.
#[derive(Clone, Debug, PartialEq)]
pub struct Localization {
    /// The pose and its covariance (None when lost).
    pub estimate: Option<Estimate>,
    /// Which path produced it.
    pub source: Source,
    /// Why (e.g. why the geometric pose was not used).
    pub reason: String,
    /// The keyframe whose group gave the geometric pose: the retrieved one, or the last
    /// frame's when the paper's locator tracked (see `reason`).
    pub keyframe: usize,
    /// PnP inliers (0 without a geometric pose).
    pub inliers: usize,
    /// The factor on the map's C_map in `estimate`'s covariance: w·max(1, n̄/n), w the weight
    /// of C_map at the pose's distance from the keyframes ([`crate::map::MapNoise::novelty_weight`],
    /// 1 without a near regime) and max(1, n̄/n) the support's
    /// ([`crate::map::MapNoise::support_scale`]); 1 when lost.
    pub map_noise_scale: f64,
    /// ν: the pose's distance from the nearest keyframe ([`crate::map::noise::pose_distance`],
    /// 10 cm or 5° = 1), which sets the map noise it carries; None when lost.
    pub novelty: Option<f64>,
    /// Time per stage.
    pub timings: Timings,
}

/// The gated fusion of a frame's geometric pose `g` with the motion prediction `m`, on the
/// parts of their covariances that are independent from frame to frame
/// ([`Estimate::pixel_covariance`]): T_F minimizes the two terms of [`fuse_gated_with`]
/// weighted by P_M and P_G, and carries
///
///   C_F = (P_M⁻¹ + P_G⁻¹)⁻¹ + (C_G − P_G),   its pixel part (P_M⁻¹ + P_G⁻¹)⁻¹,
///
/// the map error C_G − P_G shared with the history added back whole, not averaged down.
/// The gate tests T_G against T_M on P_M + C_G + `map_noise` (C_map: the history was measured
/// against other parts of the map, whose errors differ by up to C_map). None when it rejects.
///
/// # Errors
/// Covariances that are not symmetric positive definite (named as [`fuse_gated_with`] names them).
pub(crate) fn fuse_measurements(
    m: &Estimate,
    g: &Estimate,
    map_noise: &Matrix6<f64>,
    gate_sigma: f64,
    gate: Gate,
) -> Result<Option<Estimate>> {
    let shared = g.covariance - g.pixel_covariance;
    let extra = map_noise + shared;
    let (pm, cm, pg, cg) = (&m.world_from_cam, &m.pixel_covariance, &g.world_from_cam, &g.pixel_covariance);
    let f = fuse_gated_with(pm, cm, pg, cg, &extra, gate_sigma, gate)?;
    Ok((f.details == FusionSource::Fused).then(|| Estimate {
        world_from_cam: f.world_from_cam,
        covariance: f.covariance + shared,
        pixel_covariance: f.covariance,
    }))
}

/// A geometric locator's answer: the retrieved keyframe, T_G and C_G (or why not), the
/// PnP inliers.
type GeometricPose = (usize, std::result::Result<Estimate, String>, usize);

/// Localizes frame after frame against a [`Map`], keeping the motion history.
///
/// The motion model and the fusion run on the part of the uncertainty that is independent
/// from frame to frame, the pixel noise ([`Estimate::pixel_covariance`], P): the history
/// holds the geometric poses T_G, the constant-velocity fit weighs them by their P (its χ²
/// check then sees a history that moves more than the pixel noise allows and widens the
/// prediction), the prediction adds the map's process noise, and the fusion weights T_G and
/// T_M by P_G and P_M ([`fuse_measurements`]). The rest of C_G — the map points' errors,
/// which consecutive frames that see the same points share — is added back whole, never
/// averaged down. Weighted by the whole C_G, a history of one map error would pass for
/// independent measurements, the fit's χ² check would not see a history that moves, and an
/// outlying frame's pose would leak into the next ones (7-Scenes 300–399: a frame 6.9 cm off
/// kept the next eight 1–1.4 cm farther off than their single-image poses). The gate compares T_G with T_M on C_G + P_M + C_map: the
/// history was measured against other keyframe groups, whose label errors differ from the
/// current group's by up to C_map (gating on C_G + C_M alone rejected good poses after
/// every change of group and left the sequential mode coasting: 7-Scenes 600–699, 42 of
/// 100 frames motion-only, rotation 2.10° against 1.80° single; with C_map in the gate
/// 11 frames, 1.94°). The map-frame covariance C_map (label error shared by
/// consecutive frames, so it must not be averaged down) is added to whatever is returned,
/// at the support of the pose ([`crate::map::MapNoise::pose_covariance_at`]: this frame's
/// PnP inliers, the last measurement's for a motion-only frame); the gate uses C_map as it is.
/// The last frame's keyframe also serves the paper's locator as a second seed when
/// retrieval goes wrong (tracking, see `paper_pose`); [`Localizer::reset`] forgets it.
pub struct Localizer {
    map: Arc<Map>,
    options: LocalizerOptions,
    /// (timestamp, T_G with C_G and its pixel part) of the last accepted geometric
    /// measurements.
    history: VecDeque<(f64, Estimate)>,
    /// Consecutive geometric poses the gate rejected (cleared by anything else).
    rejected: Vec<(f64, Estimate)>,
    /// Consecutive motion-only frames.
    motion_only: usize,
    last_timestamp: Option<f64>,
    /// The keyframe and PnP inlier count of the last frame whose geometric pose was used
    /// (paper locator; cleared with the history).
    last_support: Option<(usize, usize)>,
    cache: HashMap<(usize, Vec<usize>), Arc<MapPoints>>,
    /// The model locator's 3D model when the map has none (built by [`Localizer::new`]).
    built_model: Option<SceneModel>,
    /// Whether the map's prepared pair matches were made with these options (they serve
    /// the paper locator's groups then).
    prepared_matches: bool,
    /// Model locator, during one frame: every accepted hypothesis with its inlier matches
    /// (step 5b refines the answer from those of its pose).
    accepted: std::sync::Mutex<Vec<model::AcceptedSolve>>,
}

/// How far apart two poses are: ‖t_a − t_b‖ (m) and the angle of R_aᵀR_b (degrees).
fn separation(a: &SE3, b: &SE3) -> (f64, f64) {
    ((a.translation - b.translation).norm(), a.rotation.distance(&b.rotation).to_degrees())
}

fn ms(start: Instant) -> f64 {
    start.elapsed().as_secs_f64() * 1e3
}

impl Localizer {
    /// A localizer with an empty history. The paper's locator, on a map whose keyframe-pair
    /// matches were prepared for these options, triangulates every keyframe's group here (in
    /// parallel) so that no frame waits for it.
    ///
    /// # Errors
    /// Options out of range, named as the Python caller spells them: `history` < 2,
    /// `gate_sigma`, `pixel_sigma` (of PnP or triangulation), `max_residual` or
    /// `epipolar_px` not finite and > 0, `top_k` 0; with the model locator on a map without a
    /// model, the errors of building one ([`SceneModel::build`], which it then does here);
    /// the model locator on a model of fewer points than `min_correspondences` (no frame
    /// could ever be placed: named `locator`); those of triangulating the paper locator's
    /// groups.
    pub fn new(map: Arc<Map>, options: LocalizerOptions) -> Result<Self> {
        let mut localizer = Self::unprepared(map, options)?;
        let points = localizer.model().map_or(0, SceneModel::len);
        if localizer.options.locator == Locator::Model && points < localizer.options.min_correspondences {
            return Err(GeolocError::invalid(
                "locator",
                format!(
                    "the map's 3D model has {points} points, fewer than the {} correspondences a pose needs (its \
                     keyframes are too close together to triangulate from), so the model locator could place no \
                     frame: use the paper's locator or map a longer recording",
                    localizer.options.min_correspondences
                ),
            ));
        }
        if localizer.options.locator == Locator::Paper && localizer.prepared_matches {
            localizer.prepare_groups()?;
        }
        Ok(localizer)
    }

    /// [`Localizer::new`] without triangulating the paper locator's groups ahead: for
    /// held-out re-localization, whose groups leave keyframes out and so are never the full
    /// ones.
    pub(crate) fn unprepared(map: Arc<Map>, options: LocalizerOptions) -> Result<Self> {
        options.check()?;
        let built_model = match (options.locator, &map.model) {
            (Locator::Model, None) => {
                Some(SceneModel::build(&map.camera, &map.keyframes, map.pose_covariances.as_deref(), &options.model)?)
            }
            _ => None,
        };
        let o = &options;
        let prepared_matches = map
            .group_matches
            .as_ref()
            .is_some_and(|m| m.options == fingerprint(&o.matching, o.epipolar_px, &o.keyframes));
        Ok(Self {
            built_model,
            prepared_matches,
            map,
            options,
            history: VecDeque::new(),
            last_support: None,
            rejected: Vec::new(),
            motion_only: 0,
            last_timestamp: None,
            cache: HashMap::new(),
            accepted: std::sync::Mutex::new(Vec::new()),
        })
    }

    /// Forgets the motion history (e.g. after a jump), and with it the last timestamp and the
    /// last frame's keyframe (tracking).
    pub fn reset(&mut self) {
        self.history.clear();
        self.last_timestamp = None;
        self.last_support = None;
        self.rejected.clear();
        self.motion_only = 0;
    }

    /// The 3D model of the model locator: the map's, or the one built for this localizer.
    fn model(&self) -> Option<&SceneModel> {
        self.map.model.as_ref().or(self.built_model.as_ref())
    }

    /// Localizes one frame: the steps retrieval, group, triangulation, PnP, fusion, each a method below.
    ///
    /// # Errors
    /// Invalid frames: keypoints and descriptors of different counts, non-finite keypoints or
    /// descriptors, a non-increasing timestamp, descriptors the map cannot compare with, a
    /// missing or wrongly sized global descriptor, a keypoint where the map's lens
    /// correction does not invert. A frame that cannot be localized is not an error: it
    /// comes back with source `Lost` and the reason.
    ///
    /// When the map estimated its camera ([`Map::with_refined_intrinsics`]) the frame's
    /// keypoints are corrected first, as the keyframes' were (u_c = K d⁻¹(K′⁻¹u)).
    pub fn localize(&mut self, frame: &Frame<'_>) -> Result<Localization> {
        let start = Instant::now();
        self.check_frame(frame)?;
        let corrected = self.map.query_keypoints(frame.keypoints)?;
        let frame = &Frame { keypoints: &corrected, ..*frame };
        let mut timings = Timings::default();
        let ((keyframe, geometric, inliers), tracked) = self.geometric_step(frame, &mut timings)?;
        // (d) motion model and (e) gated fusion
        let t = Instant::now();
        let prediction = self.predict(frame.timestamp);
        let (mut estimate, source, mut reason) = self.combine(frame.timestamp, geometric, prediction);
        if let Some(note) = tracked {
            reason = format!("{reason}; {note}");
        }
        self.last_support = match source {
            Source::Geometric | Source::Fused => Some((keyframe, inliers)),
            Source::Motion => self.last_support,
            Source::Lost => None,
        };
        // the map noise of the support the pose rests on: this frame's inliers, or for a
        // motion-only frame the last measurement's
        let (mut map_noise_scale, mut novelty) = (1.0, None);
        if let Some(e) = &mut estimate {
            let support = self.last_support.map(|(_, n)| n);
            let nu = self.map.novelty(&e.world_from_cam);
            map_noise_scale = self.map.noise.support_scale(support) * self.map.noise.novelty_weight(Some(nu));
            e.covariance += self.map.noise.covariance_at(support, Some(nu));
            novelty = Some(nu);
        }
        self.last_timestamp = Some(frame.timestamp);
        timings.motion_fusion_ms = ms(t);
        timings.total_ms = ms(start);
        Ok(Localization { estimate, source, reason, keyframe, inliers, map_noise_scale, novelty, timings })
    }

    /// Retrieval and the geometric locator. A map fused with a network is asked for its bag
    /// of words' keyframes first, and for the fused ranking only when their pose is refused
    /// or fails and that ranking differs: then the fused keyframes' pose is taken if it is
    /// accepted. So a frame the bag of words localizes gets the BoW map's answer, bit for bit
    /// — the network only adds answers — and pays for verifying the network's candidates
    /// only when BoW's keyframes failed. (Ranked first on every frame, a network candidate
    /// that verified with twice BoW's inliers replaced BoW's keyframes and cost poses: 7-Scenes
    /// frames 58 and 66 went from 2 cm to 8 and 15 cm with a GoogLeNet trained from scratch.)
    fn geometric_step(&mut self, frame: &Frame<'_>, timings: &mut Timings) -> Result<(GeometricPose, Option<String>)> {
        let k = self.retrieved_keyframes();
        let t = Instant::now();
        let words = self.map.retrieve_ranked(&frame.retrieval_query(), k, 0..0, Ranking::Words)?;
        timings.retrieval_ms = ms(t);
        let first = self.locate(frame, &words, timings)?;
        if first.0.1.is_ok() || !matches!(self.map.retrieval, Retrieval::Fused { .. }) {
            return Ok(first);
        }
        let t = Instant::now();
        let fused = self.map.retrieve_ranked(&frame.retrieval_query(), k, 0..0, Ranking::Map)?;
        timings.retrieval_ms += ms(t);
        if fused == words {
            return Ok(first);
        }
        let (second, note) = self.locate(frame, &fused, timings)?;
        if second.1.is_err() {
            return Ok(first);
        }
        let why = first.0.1.as_ref().err().map_or("", String::as_str);
        let retried = format!("retrieved with the network: the bag of words' keyframes gave no accepted pose ({why})");
        Ok((second, Some(note.map_or(retried.clone(), |n| format!("{n}; {retried}")))))
    }

    /// How many keyframes the locator retrieves: one for the paper's; for the model's
    /// 2·`top_k`, the `top_k` it solves from and the next `top_k` of the ranking (its step 11).
    fn retrieved_keyframes(&self) -> usize {
        match self.options.locator {
            Locator::Paper => 1,
            Locator::Model => self.options.top_k.saturating_mul(2),
        }
    }

    /// The geometric locator from the retrieved keyframes `top` (best first).
    fn locate(
        &mut self,
        frame: &Frame<'_>,
        top: &[usize],
        timings: &mut Timings,
    ) -> Result<(GeometricPose, Option<String>)> {
        match self.options.locator {
            Locator::Paper => self.paper_pose(frame, top[0], timings),
            Locator::Model => self.ranked_model_pose(frame, top, 0..0, timings),
        }
    }

    /// The frame's own checks (the map checks what it compares against).
    fn check_frame(&self, frame: &Frame<'_>) -> Result<()> {
        frame.descriptors.check("descriptors")?;
        let n_desc = frame.descriptors.len();
        if n_desc != frame.keypoints.len() {
            return Err(GeolocError::invalid(
                "descriptors",
                format!("{n_desc} descriptors for {} keypoints", frame.keypoints.len()),
            ));
        }
        if let Some(i) = frame.keypoints.iter().position(|k| !(k.x.is_finite() && k.y.is_finite())) {
            return Err(GeolocError::NonFinite { name: "keypoints".into(), index: i });
        }
        if let Some(sigmas) = frame.pixel_sigmas {
            if sigmas.len() != frame.keypoints.len() {
                return Err(GeolocError::invalid(
                    "pixel_sigmas",
                    format!("{} pixel_sigmas for {} keypoints", sigmas.len(), frame.keypoints.len()),
                ));
            }
            if let Some(i) = sigmas.iter().position(|s| !(s.is_finite() && *s > 0.0)) {
                return Err(GeolocError::invalid("pixel_sigmas", format!("entry {i} must be finite and > 0")));
            }
        }
        if !frame.timestamp.is_finite() || self.last_timestamp.is_some_and(|t| frame.timestamp <= t) {
            return Err(GeolocError::invalid(
                "timestamp",
                format!("must be finite and increase, got {}", frame.timestamp),
            ));
        }
        Ok(())
    }

    /// (d) the constant-velocity prediction T_M at `timestamp` from the last geometric poses
    /// weighed by their pixel parts, with the map's process noise and velocity prior: its
    /// pixel part P_M is the fit's C_M, its covariance C_M plus the latest pose's map error
    /// (C_G − P_G), which the prediction shares (None with fewer than two poses, or when the
    /// fit fails).
    fn predict(&self, timestamp: f64) -> Option<Estimate> {
        if self.history.len() < 2 {
            return None;
        }
        let ts: Vec<f64> = self.history.iter().map(|(t, _)| *t).collect();
        let poses: Vec<SE3> = self.history.iter().map(|(_, e)| e.world_from_cam).collect();
        let covs: Vec<Matrix6<f64>> = self.history.iter().map(|(_, e)| e.pixel_covariance).collect();
        let noise = &self.map.noise;
        // the fit weighs the poses by their pixel noise, independent from frame to frame; the
        // prediction shares the latest measurement's map error (the rest of its C_G)
        let latest = self.history.back().map(|(_, e)| e.covariance - e.pixel_covariance)?;
        motion_predict_with_prior(&poses, &ts, timestamp, Some(&covs), &noise.acceleration_psd, &noise.velocity_prior)
            .ok()
            .map(|p| Estimate {
                world_from_cam: p.world_from_cam,
                covariance: p.covariance + latest,
                pixel_covariance: p.covariance,
            })
    }

    /// (e) the gate and the fusion of T_G with T_M ([`fuse_measurements`]): which estimate
    /// the frame gets, its source, and why; updates the history, the rejected run and the
    /// motion-only count.
    fn combine(
        &mut self,
        timestamp: f64,
        geometric: std::result::Result<Estimate, String>,
        prediction: Option<Estimate>,
    ) -> (Option<Estimate>, Source, String) {
        match (geometric, prediction) {
            (Ok(g), Some(m)) => {
                let (gate_sigma, gate) = (self.options.gate_sigma, self.options.gate);
                // the gate allows for the group-level error C_map, the fusion weights by the
                // pixel parts only (C_map is added once, to the output, at the pose's
                // support). The gate's C_map is not scaled up for a low-support T_G: that is the
                // pose to be strict with (a gate with the scaled C_map let more wrong poses into
                // the history of maps that keep their labels: 7-Scenes 0–99, sequential recall
                // 67 % against 71 % with C_map as it is)
                match fuse_measurements(&m, &g, &self.map.noise.pose_covariance, gate_sigma, gate) {
                    Ok(Some(e)) => {
                        self.accept(timestamp, &g);
                        (Some(e), Source::Fused, "ok".to_string())
                    }
                    Ok(None) => {
                        self.rejected.push((timestamp, g));
                        match self.reinitialize() {
                            Some(done) => done,
                            None => {
                                // the image says one place, the motion another: until the
                                // images re-initialize the history (reinit_after), the
                                // prediction is answered with a covariance that holds the
                                // geometric pose too (C_M + δδᵀ) — after a jump of the
                                // camera (a robot carried away) the prediction is the wrong
                                // one, and its own σ of centimetres would hide an error of
                                // decimetres
                                let (metres, degrees) = separation(&m.world_from_cam, &g.world_from_cam);
                                let why = format!(
                                    "geometric pose outside the motion gate ({metres:.2} m / {degrees:.1}° from the \
                                     prediction, which is answered with a covariance that holds both)"
                                );
                                let (estimate, source, reason) = self.coast(m, why);
                                (estimate.map(|e| model::widened_to_hold(&e, &g)), source, reason)
                            }
                        }
                    }
                    Err(e) => {
                        self.accept(timestamp, &g);
                        (Some(g), Source::Geometric, format!("fusion skipped: {e}"))
                    }
                }
            }
            (Ok(g), None) => {
                self.accept(timestamp, &g);
                (Some(g), Source::Geometric, "ok (no motion history yet)".to_string())
            }
            (Err(why), Some(m)) => {
                self.rejected.clear();
                self.coast(m, format!("geometric locator failed: {why}"))
            }
            (Err(why), None) => {
                self.rejected.clear();
                (None, Source::Lost, format!("geometric locator failed and no motion history: {why}"))
            }
        }
    }

    /// A geometric measurement joins the history (the last `history` of them).
    fn accept(&mut self, timestamp: f64, g: &Estimate) {
        self.rejected.clear();
        self.motion_only = 0;
        self.history.push_back((timestamp, *g));
        while self.history.len() > self.options.history.max(2) {
            self.history.pop_front();
        }
    }

    /// The motion prediction alone, unless it has coasted `lost_after` frames or its
    /// position σ exceeds `max_motion_sigma_m`: then lost, with the history cleared so the
    /// next geometric pose starts afresh (a lost frame never poisons the next ones).
    fn coast(&mut self, m: Estimate, why: String) -> (Option<Estimate>, Source, String) {
        self.motion_only += 1;
        let (sigma_p, _) = isometric_sigmas(&m.covariance);
        if self.motion_only > self.options.lost_after || sigma_p > self.options.max_motion_sigma_m {
            let n = self.motion_only;
            self.history.clear();
            self.motion_only = 0;
            let reason =
                format!("{why}; lost after {n} motion-only frames (σ_p {sigma_p:.3} m), motion history cleared");
            return (None, Source::Lost, reason);
        }
        (Some(m), Source::Motion, why)
    }

    /// No lock-out: when the last N (`reinit_after`) rejected geometric poses are
    /// consecutive frames and agree with each other (the last one passes the χ²₆ gate of
    /// `gate_sigma` against the constant-velocity prediction from the others), the motion
    /// history restarts from them and the frame gets its geometric pose.
    fn reinitialize(&mut self) -> Option<(Option<Estimate>, Source, String)> {
        let n = self.options.reinit_after;
        if self.rejected.len() > n {
            self.rejected.remove(0);
        }
        if self.rejected.len() < n {
            return None;
        }
        let (t_last, last) = self.rejected[n - 1];
        let earlier = &self.rejected[..n - 1];
        let ts: Vec<f64> = earlier.iter().map(|(t, _)| *t).collect();
        let poses: Vec<SE3> = earlier.iter().map(|(_, e)| e.world_from_cam).collect();
        let covs: Vec<Matrix6<f64>> = earlier.iter().map(|(_, e)| e.covariance).collect();
        // no velocity prior here: the question is whether the run agrees with itself
        let q = &self.map.noise.acceleration_psd;
        let p = motion_predict_with_noise(&poses, &ts, t_last, Some(&covs), q).ok()?;
        let e = (p.world_from_cam.inverse() * last.world_from_cam).log();
        let info = spd_inverse(&(p.covariance + last.covariance), "covariance").ok()?;
        if (e.transpose() * info * e)[0] > chi2_6_quantile_for_sigma(self.options.gate_sigma) {
            return None;
        }
        let run = std::mem::take(&mut self.rejected);
        self.history.clear();
        for (t, g) in &run {
            self.accept(*t, g);
        }
        let reason = format!(
            "motion history re-initialized from {n} consecutive geometric poses that agree with each other but not with the prediction"
        );
        Some((Some(last), Source::Geometric, reason))
    }
}

#[cfg(test)]
mod tests {
    use nalgebra::{Vector3, Vector6};

    use super::*;
    use crate::lie::SO3;

    fn at(t: [f64; 3], pixel: f64, shared: f64) -> Estimate {
        let p = Matrix6::from_diagonal(&Vector6::repeat(pixel * pixel));
        let s = Matrix6::from_diagonal(&Vector6::repeat(shared * shared));
        Estimate { world_from_cam: SE3::new(SO3::identity(), Vector3::from(t)), covariance: p + s, pixel_covariance: p }
    }

    /// Translations only (the fusion's closed form): the mean weighted by the pixel parts,
    /// t_F = (P_M⁻¹ + P_G⁻¹)⁻¹ (P_M⁻¹ t_M + P_G⁻¹ t_G), whatever the shared part; the shared
    /// part added back to the covariance whole.
    #[test]
    fn the_fusion_weighs_the_pixel_noise_and_keeps_the_shared_map_error() {
        let m = at([0.0, 0.0, 0.0], 0.002, 0.0);
        let cases = [(0.001, 0.0), (0.001, 0.02), (0.001, 0.2)];
        for (pixel_g, shared_g) in cases {
            let g = at([0.003, -0.002, 0.001], pixel_g, shared_g);
            let f = fuse_measurements(&m, &g, &Matrix6::zeros(), 3.0, Gate::ChiSquared)
                .expect("valid")
                .expect("inside the gate");
            let (wm, wg) = (1.0 / 0.002f64.powi(2), 1.0 / pixel_g.powi(2));
            let want = g.world_from_cam.translation * wg / (wm + wg);
            assert!((f.world_from_cam.translation - want).norm() < 1e-12, "shared {shared_g}: {:?}", f.world_from_cam);
            // (the translation axes exactly; the rotation axes to the J_r of a few millimetres)
            let pixel = 1.0 / (wm + wg);
            for a in 0..6 {
                let (p, c) = (f.pixel_covariance[(a, a)], f.covariance[(a, a)]);
                assert!((p - pixel).abs() < 1e-3 * pixel, "axis {a}: {p} against {pixel}");
                assert!((c - p - shared_g * shared_g).abs() < 1e-12, "axis {a}: {c}");
            }
        }
    }

    /// The gate allows for the map errors (the geometric pose's shared part and C_map) but
    /// rejects what neither explains: 3 cm apart is 10σ of the pixel parts, 1σ with 2 cm of
    /// shared error per axis (χ²₆ at 3σ: 28.0); 30 cm is beyond both.
    #[test]
    fn the_gate_allows_for_the_map_error_and_rejects_beyond_it() {
        let m = at([0.0, 0.0, 0.0], 0.002, 0.0);
        let near = at([0.03, 0.0, 0.0], 0.002, 0.0);
        let gate = |g: &Estimate, map_noise: f64| {
            let c = Matrix6::from_diagonal(&Vector6::repeat(map_noise * map_noise));
            fuse_measurements(&m, g, &c, 3.0, Gate::ChiSquared).expect("valid").is_some()
        };
        assert!(!gate(&near, 0.0));
        assert!(gate(&at([0.03, 0.0, 0.0], 0.002, 0.02), 0.0));
        assert!(gate(&near, 0.02));
        assert!(!gate(&at([0.3, 0.0, 0.0], 0.002, 0.02), 0.02));
    }
}
