"""The float-descriptor path (SIFT, RootSIFT) against ORB on the synthetic room —
same map frames, same queries, the paper's locator in single-image mode. SIFT must localize
every query ORB does, to the same centimetre. ~15 s (SIFT extraction dominates)."""

from __future__ import annotations

import numpy as np
import pytest

import geoloc
from geoloc import datasets
from geoloc.features import FeatureExtractor
from geoloc import Localizer, Map

cv2 = pytest.importorskip("cv2")

MEDIAN_M = 0.01
MEDIAN_DEG = 0.3


def _errors(seq: datasets.Sequence, kind: str, root_sift: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Map from lap 1 (every 3rd frame), localize 10 lap-2 frames: (translation m, rotation °),
    inf when lost."""
    extract = FeatureExtractor(kind, 1000, root_sift=root_sift)  # type: ignore[arg-type]
    train = seq[0:150:3]
    feats = [extract(f.image, seq.camera) for f in train]
    assert train.poses is not None
    fmap = Map.from_features(seq.camera, train.poses, [f.keypoints for f in feats], [f.descriptors for f in feats], estimate_noise=False, refine_intrinsics=False, adjust_labels=False)
    localizer = Localizer(fmap)
    trans, rot = [], []
    for frame in seq[155:300:15]:
        f = extract(frame.image, seq.camera)
        localizer.reset()
        r = localizer.localize_features(frame.timestamp, f.keypoints, f.descriptors)
        if r.pose is None or frame.pose is None:
            trans.append(np.inf)
            rot.append(np.inf)
            continue
        t_err, r_err = geoloc.evaluation.pose_errors(r.pose, frame.pose)
        trans.append(t_err[0])
        rot.append(r_err[0])
    return np.array(trans), np.array(rot)


@pytest.mark.slow
def test_sift_and_root_sift_localize_as_well_as_orb() -> None:
    seq = datasets.synthetic_room(n_frames=300)
    orb_t, orb_r = _errors(seq, "orb")
    for root in (False, True):
        t, r = _errors(seq, "sift", root_sift=root)
        name = "RootSIFT" if root else "SIFT"
        print(f"\n{name}: median {1000 * np.median(t):.1f} mm / {np.median(r):.3f}°; ORB {1000 * np.median(orb_t):.1f} mm")
        assert np.all(np.isfinite(t[np.isfinite(orb_t)])), f"{name} lost a frame ORB localizes"
        assert np.median(t) <= max(MEDIAN_M, np.median(orb_t)) and np.median(r) <= max(MEDIAN_DEG, np.median(orb_r))
