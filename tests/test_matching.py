"""geoloc.matching against brute force and known geometry."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

import geoloc
from geoloc import lie, matching
from geoloc.montecarlo import look_at


def test_binary_matching_equals_brute_force_hamming() -> None:
    rng = np.random.default_rng(0)
    a = rng.integers(0, 256, (200, 32), dtype=np.uint8)
    b = rng.integers(0, 256, (300, 32), dtype=np.uint8)
    pairs, dist = matching.match_descriptors(a, b, ratio=None, mutual=False)
    bits = np.unpackbits(a[:, None, :] ^ b[None], axis=-1).sum(-1)
    np.testing.assert_array_equal(pairs[:, 0], np.arange(200))
    np.testing.assert_array_equal(dist, bits.min(1))
    assert np.all(bits[pairs[:, 0], pairs[:, 1]] == bits.min(1))


def test_float_copies_match_back_through_ratio_and_mutual_checks() -> None:
    rng = np.random.default_rng(1)
    a = rng.normal(size=(400, 128)).astype(np.float32)
    perm = rng.permutation(400)
    b = np.empty_like(a)
    b[perm] = a + 0.05 * rng.normal(size=a.shape).astype(np.float32)
    pairs, dist = matching.match_descriptors(a, b)
    assert len(pairs) == 400
    np.testing.assert_array_equal(pairs[:, 1], perm[pairs[:, 0]])
    assert dist.dtype == np.float32


def test_epipolar_filter_rejects_off_line_pairs() -> None:
    cam = geoloc.Camera(525, 525, 320, 240)
    target = np.array([0.0, 0.0, 5.0])
    pa, pb = look_at(np.array([-0.3, 0.0, 0.0]), target), look_at(np.array([0.3, 0.1, 0.0]), target)
    pts = target + np.random.default_rng(2).normal(size=(100, 3))

    def project(T: np.ndarray) -> np.ndarray:
        p = lie.se3_transform_points(lie.se3_inverse(T), pts)
        return p[:, :2] / p[:, 2:] * 525 + [320, 240]

    ka, kb = project(pa), project(pb)
    kb[:20, 1] += 40
    pairs = np.c_[np.arange(100), np.arange(100)]
    keep = matching.epipolar_filter(cam, pa, pb, ka, kb, pairs, max_px=2.0)
    assert keep[20:].all()
    # against OpenCV's Sampson distance (squared pixels) with F from the relative pose
    rel = lie.se3_compose(lie.se3_inverse(pb), pa)
    t = rel[:3, 3]
    e = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]]) @ rel[:3, :3]
    k_inv = np.linalg.inv(cam.K)
    f = k_inv.T @ e @ k_inv
    sampson = np.array([cv2.sampsonDistance(np.r_[a, 1.0], np.r_[b, 1.0], f) for a, b in zip(ka, kb)])
    np.testing.assert_array_equal(keep, np.sqrt(sampson) <= 2.0)
    assert (~keep[:20]).sum() >= 10


def test_bad_input() -> None:
    a8 = np.zeros((3, 32), dtype=np.uint8)
    with pytest.raises(geoloc.InvalidInputError, match="binary .* cannot be compared"):
        matching.match_descriptors(a8, np.zeros((3, 32), dtype=np.float32))
    with pytest.raises(geoloc.InvalidInputError, match="width 16 differs"):
        matching.match_descriptors(a8, np.zeros((3, 16), dtype=np.uint8))
    with pytest.raises(geoloc.InvalidInputError, match="ratio"):
        matching.match_descriptors(a8, a8, ratio=1.5)
    with pytest.raises(geoloc.InvalidInputError, match=r"descriptors_a: expected shape \(N, W\)"):
        matching.match_descriptors(np.zeros(5), a8)
    cam = geoloc.Camera(1, 1, 0, 0)
    # the errors name the Python arguments, pairs and max_px (were matches, max_epipolar_px)
    with pytest.raises(geoloc.InvalidInputError, match=r"^pairs: "):
        matching.epipolar_filter(cam, np.eye(4), np.eye(4), np.zeros((1, 2)), np.zeros((1, 2)), np.array([[3, 0]]))
    with pytest.raises(geoloc.InvalidInputError, match=r"^max_px: "):
        matching.epipolar_filter(cam, np.eye(4), np.eye(4), np.zeros((1, 2)), np.zeros((1, 2)), np.array([[0, 0]]), max_px=-1)
    with pytest.raises(geoloc.InvalidInputError, match=r"^pairs: "):
        matching.epipolar_filter(cam, np.eye(4), np.eye(4), np.zeros((1, 2)), np.zeros((1, 2)), np.array([[-1, 0]]))
    pairs, dist = matching.match_descriptors(a8, np.zeros((0, 32), dtype=np.uint8))
    assert pairs.shape == (0, 2) and dist.shape == (0,)


def test_self_matches_at_extreme_magnitudes() -> None:
    """Float32 values near 1e20 are finite but their squares are not; matching used
    to find 0 of 50 self-matches there."""
    x = (np.random.default_rng(0).normal(size=(50, 16)) * 1e20).astype(np.float32)
    pairs, dist = matching.match_descriptors(x, x)
    assert len(pairs) == 50 and np.all(pairs[:, 0] == pairs[:, 1]) and np.all(dist == 0)


@pytest.mark.parametrize("scale", [512.0, 1.0])  # OpenCV SIFT rows have norm ≈ 512, RootSIFT rows norm 1
def test_float_matching_equals_brute_force_in_euclidean_units(scale: float) -> None:
    """Every float threshold is in the units of the Euclidean distance (not its
    square, not bits): the ratio test d₁ < r·d₂, the mutual check and ``max_distance`` give
    exactly the brute-force selection, for SIFT-sized and RootSIFT-sized rows."""
    rng = np.random.default_rng(5)
    a = np.abs(rng.normal(size=(150, 128))).astype(np.float32)
    b = np.concatenate([a[:100] + 0.3 * np.abs(rng.normal(size=(100, 128))), np.abs(rng.normal(size=(120, 128)))])
    a *= np.float32(scale) / np.linalg.norm(a, axis=1, keepdims=True)
    b = (np.float32(scale) * b / np.linalg.norm(b, axis=1, keepdims=True)).astype(np.float32)
    d = np.linalg.norm(a[:, None, :].astype(np.float64) - b[None].astype(np.float64), axis=-1)
    order = np.sort(d, axis=1)
    nearest, back = d.argmin(1), d.argmin(0)
    first = np.sort(order[:, 0])
    max_distance = float(first[75] + first[76]) / 2  # between two rows: no boundary ties in f32
    for ratio, limit in ((0.8, None), (0.9, max_distance), (None, None)):
        pairs, dist = matching.match_descriptors(a, b, ratio=ratio, mutual=True, max_distance=limit)
        keep = back[nearest] == np.arange(len(a))
        if ratio is not None:
            keep &= order[:, 0] < ratio * order[:, 1]
        if limit is not None:
            keep &= order[:, 0] <= limit
        np.testing.assert_array_equal(pairs[:, 0], np.flatnonzero(keep))
        np.testing.assert_array_equal(pairs[:, 1], nearest[keep])
        np.testing.assert_allclose(dist, order[keep, 0], rtol=1e-5)
