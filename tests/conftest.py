"""Shared pytest configuration: hypothesis profiles and the path to the shared sample data."""

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
