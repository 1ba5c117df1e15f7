"""Shared pytest configuration: the hypothesis profiles.

Test tiers: ``python -m pytest`` runs everything (what .ci/run runs); ``python -m pytest -m
"not slow"`` leaves out the tests marked ``slow`` (training, the 3D-model locator, mypy and
stubtest, the robot binary, the real 7-Scenes runs, the adversarial fuzzing) and takes about
two minutes on 2 cores."""

from __future__ import annotations

import os

from hypothesis import HealthCheck, settings

# "fast" for local iteration, "ci" (more examples, derandomized so CI is reproducible).
settings.register_profile("fast", max_examples=50, deadline=None)
settings.register_profile(
    "ci",
    max_examples=300,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow],
)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci" if os.environ.get("CI") else "fast"))
