"""One front door: ``geoloc.Map`` (from images or from features) and ``geoloc.Localizer``
(images or features), one result type, every default the core's — the same in Python, in the
``geoloc`` CLI and in ``geoloc-rs`` — and the former names still working, with a warning."""

from __future__ import annotations

import inspect
import json
import re
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

import geoloc
from geoloc import _core, datasets
from geoloc.features import FeatureExtractor
from test_robot import geoloc_rs  # noqa: F401  (the session fixture that builds the binary)

#: The options whose default is the core's: a Python signature must say None for each.
BUILD_OPTIONS = set(_core.build_defaults())
LOCALIZER_OPTIONS = set(_core.localizer_defaults())


@pytest.fixture(scope="module")
def room() -> tuple[datasets.Sequence, datasets.Sequence]:
    seq = datasets.synthetic_room(n_frames=120, seed=0)
    return seq[0:60:3], seq[61:70:2]


def test_the_core_reports_its_defaults_once() -> None:
    assert geoloc.Map.default_options() == _core.build_defaults()
    assert geoloc.Localizer.default_options() == _core.localizer_defaults()
    build, local = _core.build_defaults(), _core.localizer_defaults()
    assert build["estimate_noise"] and build["refine_intrinsics"] and build["adjust_labels"] and build["model"]
    assert local["locator"] == "model" and local["history"] >= 2 and local["pixel_sigma"] > 0


@pytest.mark.parametrize(
    "function, options",
    [
        (geoloc.Map.build, BUILD_OPTIONS - {"retrieval"}),
        (geoloc.Map.from_features, BUILD_OPTIONS),
        (geoloc.Localizer.__init__, LOCALIZER_OPTIONS),
    ],
    ids=["Map.build", "Map.from_features", "Localizer"],
)
def test_python_signatures_leave_every_core_option_to_the_core(function: object, options: set[str]) -> None:
    parameters = inspect.signature(function).parameters  # type: ignore[arg-type]
    missing = options - set(parameters)
    assert not missing, f"{missing} cannot be set"
    spelled = {name: parameters[name].default for name in options if parameters[name].default is not None}
    assert not spelled, f"defaults spelled in Python instead of the core's: {spelled}"


def test_both_paths_build_the_same_map_and_give_the_same_answer(room: tuple[datasets.Sequence, datasets.Sequence]) -> None:
    """Map.build (images) and Map.from_features (the same features) with no options: one
    map, the same defaults (noise, camera and labels estimated), bit-identical results."""
    train, test = room
    from_images = geoloc.Map.build(train)
    extractor = FeatureExtractor("orb", 1000)
    feats = [extractor(train.gray(i), train.camera) for i in range(len(train))]
    timestamps = train.timestamps
    from_features = geoloc.Map.from_features(
        train.camera, train.poses, [f.keypoints for f in feats], [f.descriptors for f in feats], timestamps=timestamps
    )
    for m in (from_images, from_features):
        assert m.labels is not None and m.self_calibration is not None
        assert np.any(m.map_noise["pose_covariance"])
    np.testing.assert_array_equal(from_images.keyframe_poses, from_features.keyframe_poses)
    np.testing.assert_array_equal(from_images.map_noise["pose_covariance"], from_features.map_noise["pose_covariance"])
    by_image, by_features = geoloc.Localizer(from_images), geoloc.Localizer(from_features)
    for i in range(len(test)):
        t = float(test.timestamps[i])
        a = by_image.localize(test.gray(i), t)
        f = extractor(test.gray(i), test.camera)
        b = by_features.localize_features(t, f.keypoints, f.descriptors, pixel_sigmas=f.pixel_sigmas)
        assert isinstance(a, geoloc.Localization) and isinstance(b, geoloc.Localization)
        assert (a.source, a.reason, a.keyframe, a.inliers) == (b.source, b.reason, b.keyframe, b.inliers)
        if a.pose is not None:
            np.testing.assert_array_equal(a.pose, b.pose)
            np.testing.assert_array_equal(a.covariance, b.covariance)
        assert set(b.timings) == {"retrieval", "keyframes", "map_points", "matching", "pnp", "motion_fusion", "total"}
        assert {"decode", "features"} <= set(a.timings)
    with pytest.raises(geoloc.InvalidInputError, match=r"^image: .*localize_features"):
        by_features.localize(test.gray(0), 99.0)


def test_a_localizer_reports_the_options_it_runs_with(room: tuple[datasets.Sequence, datasets.Sequence]) -> None:
    train, _ = room
    m = geoloc.Map.build(train, estimate_noise=False, refine_intrinsics=False, adjust_labels=False)
    assert geoloc.Localizer(m).options == _core.localizer_defaults()
    set_ = geoloc.Localizer(m, pixel_sigma=0.5, max_residual=4.0, gate_sigma=2.0, history=6, locator="model", top_k=3).options
    assert set_ == {"pixel_sigma": 0.5, "max_residual": 4.0, "gate_sigma": 2.0, "history": 6, "locator": "model", "top_k": 3}
    with pytest.raises(geoloc.InvalidInputError, match=r"^gate_sigma: "):
        geoloc.Localizer(m, gate_sigma=-1.0)
    # the binding refuses an option the core does not have, naming it and listing the known ones
    with pytest.raises(geoloc.InvalidInputError, match=r"^pixel_sigmaa: not an option; expected one of pixel_sigma, "):
        _core.FeatureLocalizer(m._core, options={"pixel_sigmaa": 1.0})
    with pytest.raises(geoloc.InvalidInputError, match=r"^models: not an option; expected one of retrieval, "):
        _core.FeatureMap(train.camera.intrinsics, train.poses[:1].reshape(1, 16), [np.zeros((0, 2))], [np.zeros((0, 32), np.uint8)], options={"models": True})
    with pytest.raises(geoloc.InvalidInputError, match=r"^depth: "):
        geoloc.Map.from_features(train.camera, train.poses[:1], [np.zeros((0, 2))], [np.zeros((0, 32), np.uint8)], depth=-1)


def _help_defaults(text: str) -> dict[str, str]:
    """``--option … [default: value]`` pairs of a clap help text."""
    found = {}
    for block in re.split(r"\n\s*(?=--)", text):
        name = re.match(r"--([\w-]+)", block.strip())
        value = re.search(r"\[default: ([^\]]+)\]", block)
        if name and value:
            found[name.group(1).replace("-", "_")] = value.group(1)
    return found


def test_geoloc_rs_shows_the_core_defaults(geoloc_rs: Path) -> None:  # noqa: F811
    shown = _help_defaults(subprocess.run([str(geoloc_rs), "localize", "--help"], capture_output=True, text=True, check=True).stdout)
    for name, value in _core.localizer_defaults().items():
        assert name in shown, f"geoloc-rs localize has no --{name.replace('_', '-')}"
        assert shown[name] == str(value) or float(shown[name]) == value, (name, shown[name], value)


def test_the_cli_leaves_unset_options_to_the_core(tmp_path: Path) -> None:
    from geoloc.cli import build_parser

    parser, _ = build_parser()
    (tmp_path / "m.geoloc").write_bytes(b"")
    build = parser.parse_args(["build-map", "--format", "synthetic", "--out", "m.geoloc"])
    assert (build.refine_intrinsics, build.adjust_labels, build.model) == (None, None, None)
    assert parser.parse_args(["build-map", "--format", "synthetic", "--out", "m.geoloc", "--keep-labels", "--nominal-intrinsics"]).adjust_labels is False
    localize = parser.parse_args(["localize", "--map", str(tmp_path / "m.geoloc"), "--format", "synthetic", "--out", "p.txt"])
    assert localize.locator is None
    # the Python side's own defaults (features are extracted in Python) are Map.build's
    signature = inspect.signature(geoloc.Map.build).parameters
    assert (build.features, build.n_features) == (signature["features"].default, signature["n_features"].default)


def test_the_former_names_work_and_warn(room: tuple[datasets.Sequence, datasets.Sequence], tmp_path: Path) -> None:
    train, test = room
    extractor = FeatureExtractor("orb", 1000)
    feats = [extractor(train.gray(i), train.camera) for i in range(len(train))]
    args = (train.camera, train.poses, [f.keypoints for f in feats], [f.descriptors for f in feats])
    with pytest.warns(DeprecationWarning, match="Map.from_features"):
        old = geoloc.localizer.FeatureMap(*args)
    # its former defaults: nothing estimated, as old code expects
    assert old.labels is None and old.self_calibration is None and not np.any(old.map_noise["pose_covariance"])
    with pytest.warns(DeprecationWarning, match="localize_features"):
        old_loc = geoloc.localizer.FeatureLocalizer(old)
    f = extractor(test.gray(0), test.camera)
    r = old_loc.localize(0.0, f.keypoints, f.descriptors)
    new = geoloc.Localizer(
        geoloc.Map.from_features(*args, estimate_noise=False, refine_intrinsics=False, adjust_labels=False)
    ).localize_features(0.0, f.keypoints, f.descriptors)
    assert r.source == new.source and (r.pose is None or np.array_equal(r.pose, new.pose))
    with pytest.warns(DeprecationWarning, match="use .timings"):
        assert r.timings_ms is r.timings
    with pytest.warns(DeprecationWarning):
        assert geoloc.localizer.LocalizationResult is geoloc.Localization
    with pytest.warns(DeprecationWarning):
        assert geoloc.mapping.MapLocalization is geoloc.Localization
    with pytest.warns(DeprecationWarning):
        assert geoloc.mapping.Localizer is geoloc.Localizer
    # a file the former FeatureMap saved (its caller's settings, no frontend record) loads as
    # a map built from features
    path = tmp_path / "old.geoloc"
    old._core.save(str(path), json.dumps({"caller": "settings"}))
    with pytest.warns(DeprecationWarning, match="FeatureMap"):
        back = geoloc.Map.load(path)
    assert back.features is None and len(back) == len(old)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert geoloc.Localizer(back).localize_features(0.0, f.keypoints, f.descriptors).source == new.source


def test_the_public_surface_is_what_a_user_needs() -> None:
    exported = set(geoloc.__all__)
    assert {"Map", "Localizer", "Localization", "Camera", "datasets", "lie", "geometry"} <= exported
    assert not {name for name in exported if name.startswith("_") and name != "__version__"}
    assert "FeatureMap" not in exported and "FeatureLocalizer" not in exported
    # importing geoloc imports no training code (torch stays optional)
    probe = subprocess.run([sys.executable, "-c", "import geoloc, sys; print('torch' in sys.modules)"], capture_output=True, text=True)
    assert probe.stdout.strip() == "False", probe.stderr
