"""Local features from OpenCV (ORB or SIFT) in the form the core wants.

Keypoints come out **undistorted** (``Camera.undistort_points``: the core's projection has no
distortion), with each keypoint's positional uncertainty from its detector scale:

* ORB detects on a pyramid whose level L is downscaled by ``scaleFactor``^L (1.2^L by
  default); a keypoint found there is only good to about one pixel *of that level*, so
  ``pixel_sigma = scaleFactor ** octave`` (in full-resolution pixels; ``octaves`` = L).
* SIFT packs its scale into ``KeyPoint.octave``: the low byte is the octave o as a signed
  8-bit number (−1 when found on the 2× upsampled first octave), the next byte the layer l
  within the octave (1 … nOctaveLayers). Pixels of octave o are 2^o full-resolution pixels
  and layer l adds a factor 2^(l/nOctaveLayers) of blur, so
  ``pixel_sigma = 2 ** (o + (l - 1) / nOctaveLayers)`` (0.5 for the finest keypoints) and
  ``octaves`` = o. (``KeyPoint.size`` ≈ 2·1.6·2^(o + l/nOctaveLayers) is consistent with it.)

The localizer weights each query keypoint by this σ in PnP (times its ``pixel_sigma``):
weighted least squares is the efficient estimator when the noise differs between keypoints.

Descriptors: ORB (N, 32) uint8 (binary, Hamming); SIFT (N, 128) float32 (L2), or RootSIFT
(Arandjelović & Zisserman 2012: L1-normalize, square root) with ``root_sift=True``.
Extraction is deterministic (OpenCV's detectors are, for a given image and options).

Per descriptor kind downstream: bag-of-words retrieval uses 10³ words for both
kinds and counts a word's occurrences for ORB but only its presence for SIFT/RootSIFT
(:class:`geoloc.retrieval.BowDatabase`: SIFT's bursts on repetitive texture); matching uses
the same unit-free thresholds for both (Lowe's ratio 0.8 on Hamming bits or on the L2
distance, no absolute limit; ``MatchOptions`` in the core).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from ._opencv import import_cv2
from .camera import Camera
from .exceptions import InvalidInputError

__all__ = ["FeatureExtractor", "Features", "decode_sift_octave"]

#: The feature kind and the features per image a map uses unless told otherwise (the
#: Python side's defaults: features are extracted here, not in the core).
DEFAULT_KIND: Literal["orb", "sift"] = "orb"
DEFAULT_N_FEATURES = 1000

ORB_SCALE_FACTOR = 1.2
ORB_LEVELS = 8
SIFT_OCTAVE_LAYERS = 3
#: SIFT's DoG contrast threshold (OpenCV's ``contrastThreshold``; Lowe's 0.04 is OpenCV's
#: default). With 0.04, ``n_features=1000`` gave a median of 832 and a 5th percentile of 348
#: keypoints on the 7-Scenes kitchen frames (low texture, motion blur), while ORB keeps its
#: n best by Harris score (~950); an image with few keypoints matches and triangulates little
#: and skews bag-of-words scores. A quarter of it lets ``n_features`` decide, as for ORB:
#: OpenCV keeps the ``n_features`` strongest DoG responses.
SIFT_CONTRAST_THRESHOLD = 0.01
ORB_DESCRIPTOR_BYTES = 32
SIFT_DESCRIPTOR_SIZE = 128


@dataclass(frozen=True, eq=False)
class Features:
    """Keypoints of one image: ``keypoints`` (N, 2) float64 undistorted pixels (x, y);
    ``descriptors`` (N, 32) uint8 (ORB) or (N, 128) float32 (SIFT); ``octaves`` (N,) int
    (ORB pyramid level, SIFT signed octave); ``pixel_sigmas`` (N,) float64 positional σ in
    pixels from the detector scale (see the module doc); ``responses`` (N,) detector scores."""

    keypoints: NDArray[np.float64]
    descriptors: NDArray[Any]
    octaves: NDArray[np.int64]
    pixel_sigmas: NDArray[np.float64]
    responses: NDArray[np.float64]

    def __len__(self) -> int:
        return len(self.keypoints)


def decode_sift_octave(packed: NDArray[Any]) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """OpenCV SIFT's packed ``KeyPoint.octave`` → (octave o as signed, layer l)."""
    raw = np.asarray(packed)
    if raw.dtype.kind not in "iu":
        raise InvalidInputError(f"packed: expected integers (KeyPoint.octave), got an array of dtype {raw.dtype}")
    p = raw.astype(np.int64)
    octave = p & 0xFF
    octave = np.where(octave >= 128, octave - 256, octave)
    layer = (p >> 8) & 0xFF
    return octave, layer


#: Largest ``n_features`` a FeatureExtractor accepts (OpenCV's detectors take a C int).
MAX_FEATURES = 1_000_000


class FeatureExtractor:
    """``FeatureExtractor(kind="orb"|"sift", n_features=1000, root_sift=False)(image, camera)``
    → :class:`Features`. ``image``: (H, W) gray or (H, W, 3) BGR uint8 of the camera's size."""

    def __init__(
        self, kind: Literal["orb", "sift"] = DEFAULT_KIND, n_features: int = DEFAULT_N_FEATURES, root_sift: bool = False
    ) -> None:
        if kind not in ("orb", "sift"):
            raise InvalidInputError(f"kind: expected 'orb' or 'sift', got {kind!r}")
        if not isinstance(n_features, (int, np.integer)) or isinstance(n_features, bool) or n_features < 1:
            raise InvalidInputError(f"n_features: expected a positive integer, got {n_features!r}")
        if n_features > MAX_FEATURES:  # OpenCV takes a C int: 2**63 raised OverflowError
            raise InvalidInputError(f"n_features: must be at most {MAX_FEATURES}, got {n_features}")
        if not isinstance(root_sift, (bool, np.bool_)):
            raise InvalidInputError(f"root_sift: expected True or False, got {root_sift!r:.40}")
        if root_sift and kind != "sift":
            raise InvalidInputError("root_sift: only applies to SIFT features (kind / features 'sift')")
        cv2 = import_cv2("feature extraction")
        self.kind = kind
        self.n_features = int(n_features)
        self.root_sift = bool(root_sift)
        if kind == "orb":
            self._detector = cv2.ORB_create(nfeatures=self.n_features, scaleFactor=ORB_SCALE_FACTOR, nlevels=ORB_LEVELS)
        else:
            self._detector = cv2.SIFT_create(
                nfeatures=self.n_features, nOctaveLayers=SIFT_OCTAVE_LAYERS, contrastThreshold=SIFT_CONTRAST_THRESHOLD
            )
        self._cv2 = cv2

    def __repr__(self) -> str:
        return f"FeatureExtractor(kind={self.kind!r}, n_features={self.n_features}, root_sift={self.root_sift})"

    @property
    def descriptor_shape(self) -> tuple[int, np.dtype[Any]]:
        """(width, dtype) of one descriptor row."""
        if self.kind == "orb":
            return ORB_DESCRIPTOR_BYTES, np.dtype(np.uint8)
        return SIFT_DESCRIPTOR_SIZE, np.dtype(np.float32)

    def __call__(self, image: NDArray[Any], camera: Camera) -> Features:
        gray = self.gray(image, camera)  # checks the camera, then the image
        kps, desc = self._detector.detectAndCompute(gray, None)
        width, dtype = self.descriptor_shape
        if desc is None or len(kps) == 0:
            return Features(
                np.zeros((0, 2)), np.zeros((0, width), dtype=dtype), np.zeros(0, dtype=np.int64), np.zeros(0), np.zeros(0)
            )
        pts = np.array([kp.pt for kp in kps], dtype=np.float64)
        packed = np.array([kp.octave for kp in kps], dtype=np.int64)
        responses = np.array([kp.response for kp in kps], dtype=np.float64)
        if self.kind == "orb":
            octaves = packed
            sigmas = ORB_SCALE_FACTOR ** octaves.astype(np.float64)
            descriptors = np.ascontiguousarray(desc, dtype=np.uint8)
        else:
            octaves, layers = decode_sift_octave(packed)
            sigmas = 2.0 ** (octaves + (layers - 1) / SIFT_OCTAVE_LAYERS)
            descriptors = np.ascontiguousarray(desc, dtype=np.float32)
            if self.root_sift:
                l1 = np.maximum(np.abs(descriptors).sum(axis=1, keepdims=True), np.float32(1e-12))
                descriptors = np.sqrt(descriptors / l1).astype(np.float32)
        return Features(camera.undistort_points(pts), descriptors, octaves, sigmas.astype(np.float64), responses)

    def gray(self, image: NDArray[Any], camera: Camera) -> NDArray[np.uint8]:
        """The (H, W) uint8 grey image features are extracted from: ``image`` as given when
        grey, OpenCV's BGR → grey conversion when (H, W, 3) BGR; checked against ``camera``'s
        size (:class:`~geoloc.InvalidInputError` naming ``image``, or ``camera`` when it is not a
        :class:`~geoloc.Camera`)."""
        if not isinstance(camera, Camera):
            raise InvalidInputError(f"camera: expected a geoloc.Camera, got {type(camera).__name__}")
        img = np.asarray(image)
        if img.dtype != np.uint8:
            raise InvalidInputError(f"image: expected uint8 pixels, got dtype {img.dtype}")
        if img.ndim in (2, 3) and 0 in img.shape[:2]:  # OpenCV asserts on an empty image
            raise InvalidInputError(f"image: is empty, shape {img.shape}")
        if img.ndim == 3 and img.shape[2] == 3:
            gray = self._cv2.cvtColor(np.ascontiguousarray(img), self._cv2.COLOR_BGR2GRAY)
        elif img.ndim == 2:
            gray = img
        else:
            raise InvalidInputError(f"image: expected (H, W) gray or (H, W, 3) BGR, got shape {img.shape}")
        if gray.shape != (camera.height, camera.width):
            raise InvalidInputError(
                f"image: is {gray.shape[1]}×{gray.shape[0]}, the camera is {camera.width}×{camera.height}"
            )
        return np.ascontiguousarray(gray)
