"""A `geometric` answer is a claim: queries a map does not cover must not come back as confident
poses metres off. On the shared 7-Scenes frames, a map of frames 0–59 (every 2nd, with its 3D
model) and queries from elsewhere in the kitchen — the case where, before the acceptance
rule, 21 of 30 model-locator answers were `geometric` and up to 6 m / 136° off with
decimetre σ. Every answer either is within 0.5 m / 10° of the label with its error inside the
99.9 % χ²₆ region of the returned covariance, or is not `geometric`/`fused` and says why.
Also: the map's noise, which 30 keyframes cannot estimate, is the documented default — never
zero — and the map says so.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import geoloc
from geoloc import _core, evaluation

KITCHEN = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "7scenes-redkitchen"

#: Query frames far (≥ 40 frames) from the map's keyframes 0–58, and a few it covers.
FAR = list(range(100, 700, 40))
COVERED = [1, 13, 29, 45]
CHI2_6_999 = 22.457744484825326


def _kitchen_map(first: int, stop: int, step: int):
    """The shared kitchen sequence and a map (with its 3D model) of its frames first:stop:step."""
    if not KITCHEN.is_dir():
        pytest.skip(f"shared sample data not found at {KITCHEN} (see ../shared/data/README.md)")
    from geoloc.datasets import load_7scenes

    seq = load_7scenes(KITCHEN)
    return seq, geoloc.Map.build(seq[list(range(first, stop, step))], model=True)


@pytest.fixture(scope="module")
def small_map():
    return _kitchen_map(0, 60, 2)


@pytest.mark.parametrize("locator", ["paper", "model"])
def test_uncovered_queries_are_not_reported_as_confident_poses(small_map, locator):
    seq, the_map = small_map
    loc = geoloc.Localizer(the_map, locator=locator)
    reported = 0
    for i in COVERED + FAR:
        loc.reset()
        r = loc.localize(seq.gray(i), i / 30.0)
        if r.source not in ("geometric", "fused"):
            assert r.pose is None and r.reason, (i, r.reason)
            continue
        reported += 1
        truth = seq.poses[i]
        position, rotation = evaluation.pose_errors(r.pose[None], truth[None])
        assert position[0] <= 0.5 and rotation[0] <= 10.0, (i, position, rotation, r.inliers)
        assert evaluation.nees(r.pose[None], r.covariance[None], truth[None])[0] <= CHI2_6_999, i
    # the covered frames still come back (the rule must not buy honesty with recall)
    assert reported >= len(COVERED) - 1


@pytest.fixture(scope="module")
def map_100():
    return _kitchen_map(0, 300, 3)


@pytest.mark.slow
def test_the_model_locator_reports_only_poses_the_map_confirms(map_100):
    """Frames 370 and 690 against a map of 0–297: the retrieval matches of the top keyframes
    fit a pose 0.9 m / 143° and 0.75 m / 24° off with no σ or viewpoint objection; guided
    matching near that pose finds fewer inliers than the retrieval matches, so it is not
    reported. For 690 the best-ranked keyframe's matches alone (the second hypothesis) give
    the right pose, which is; 370 has none. Covered frames are reported."""
    seq, the_map = map_100
    loc = geoloc.Localizer(the_map, locator="model")
    for i in (370, 690, 1, 100, 200):
        loc.reset()
        r = loc.localize(seq.gray(i), i / 30.0)
        if i == 370:
            assert r.source == "lost" and "not confirmed by the map" in r.reason, (i, r.source, r.reason)
            continue
        assert r.source == "geometric", (i, r.reason)
        position, rotation = evaluation.pose_errors(r.pose[None], seq.poses[i][None])
        assert position[0] <= 0.1 and rotation[0] <= 3.0, (i, position, rotation)
        assert evaluation.nees(r.pose[None], r.covariance[None], seq.poses[i][None])[0] <= CHI2_6_999, i


def test_a_map_too_small_to_estimate_its_noise_uses_the_default_and_says_so(small_map):
    _, the_map = small_map
    noise = the_map.map_noise
    assert noise["holdout_samples"] < _core.MIN_NOISE_SAMPLES
    sigma = np.sqrt(np.diag(noise["pose_covariance"]))
    np.testing.assert_allclose(sigma, [0.05] * 3 + [np.radians(2.0)] * 3, rtol=1e-12)
    assert noise["pose_covariance_source"].startswith("default:"), noise["pose_covariance_source"]


@pytest.mark.slow
def test_out_of_map_frames_a_small_maps_best_keyframe_refuses_need_the_nearest_keyframes():
    """Frames 460, 660 and 680 against a map of frames 500–599, single image: the best-ranked
    keyframe's own matches were refused, and the union's or a lower-ranked keyframe's matches
    fit a pose 0.56–1.56 m off with σ of 5–12 cm (NEES 97–372 against the SfM reference),
    which the keyframes nearest it do not confirm. Each comes back not `geometric`, naming
    that, or within 0.5 m / 10° of the reference and inside its 99.9 % region; the map's own
    frames are still answered."""
    from geoloc.reference import align_reference, load_reference, match_reference

    reference = KITCHEN.parent / "7scenes-redkitchen-reference" / "sfm-poses.txt"
    seq, the_map = _kitchen_map(500, 600, 1)
    if not reference.is_file():
        pytest.skip(f"the shared SfM reference is absent ({reference})")
    keys, poses = load_reference(reference)
    alignment = align_reference(poses[match_reference(keys, np.arange(500, 600))], the_map.keyframe_poses)
    loc = geoloc.Localizer(the_map, locator="model")
    frames = [460, 660, 680, 520, 570]
    truth = alignment.apply(poses[match_reference(keys, np.array(frames))])
    for i, t in zip(frames, truth):
        loc.reset()
        r = loc.localize(seq.gray(i), i / 30.0)
        if 500 <= i < 600:
            assert r.source == "geometric", (i, r.reason)
        if r.source != "geometric":
            assert r.pose is None and "not confirmed" in r.reason, (i, r.reason)
            continue
        position, rotation = evaluation.pose_errors(r.pose[None], t[None])
        assert position[0] <= 0.5 and rotation[0] <= 10.0, (i, position, rotation, r.inliers)
        assert evaluation.nees(r.pose[None], r.covariance[None], t[None])[0] <= CHI2_6_999, i
