"""Shared fixtures."""

from __future__ import annotations

import pytest

from pipeline.fit import MeasuredProfile

from .reference_profiles import deon_profile


@pytest.fixture
def deon() -> MeasuredProfile:
    return deon_profile()
