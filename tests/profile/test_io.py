"""Profile CSV and fit JSON at the stage boundary."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from skinpipe.errors import InputError
from skinpipe.profile.fit import fit_sum_of_gaussians
from skinpipe.profile.io import (
    read_fit_inputs,
    read_fit_json,
    read_profile_csv,
    write_fit_json,
    write_profile_csv,
)
from skinpipe.profile.types import MeasuredProfile

from ..reference_profiles import deon_profile


def test_csv_round_trip_with_stddev(tmp_path: Path) -> None:
    prof = deon_profile()
    prof = MeasuredProfile(prof.radius_mm, prof.values, 0.01 * prof.values + 1e-6)
    path = write_profile_csv(tmp_path / "forehead.csv", prof)
    back = read_profile_csv(path)
    assert back.name == "forehead"
    np.testing.assert_allclose(back.radius_mm, prof.radius_mm, rtol=1e-8)
    np.testing.assert_allclose(back.values, prof.values, rtol=1e-8)
    assert back.stddev is not None
    np.testing.assert_allclose(back.stddev, prof.stddev, rtol=1e-8)


@pytest.mark.parametrize(
    ("content", "message"),
    [
        ("", "empty file"),
        ("radius_mm,R,G\n0,1,1\n", "missing column"),
        ("radius_mm,R,G,B\n", "header only"),
        ("radius_mm,R,G,B\n0,1,x,1\n", "line 2, column G: 'x' is not a number"),
        ("radius_mm,R,G,B\n0,1,1\n", "line 2, column B: '<missing>'"),
    ],
)
def test_bad_csv_names_file_and_place(tmp_path: Path, content: str, message: str) -> None:
    path = tmp_path / "bad.csv"
    path.write_text(content)
    with pytest.raises(InputError, match=message) as info:
        read_profile_csv(path)
    assert "bad.csv" in str(info.value)


def test_missing_csv(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="no such file"):
        read_profile_csv(tmp_path / "nope.csv")


def test_fit_json_round_trip(tmp_path: Path) -> None:
    fit = fit_sum_of_gaussians(deon_profile(), k=3)
    path = write_fit_json(tmp_path / "fit.json", fit)
    back = read_fit_json(path)
    # FIT.json holds float32-exact numbers (what USD float attributes store)
    f32 = lambda a: np.asarray(a, np.float32).astype(np.float64)  # noqa: E731
    np.testing.assert_array_equal(back.variances_mm2, f32(fit.variances_mm2))
    np.testing.assert_array_equal(back.weights, f32(fit.weights))
    np.testing.assert_array_equal(back.error, f32(fit.error))
    assert read_fit_inputs([tmp_path])[0].name == fit.name


@pytest.mark.parametrize(
    ("content", "message"),
    [
        ("{", "not valid JSON"),
        ("[]", "JSON object"),
        ('{"terms": []}', "no terms"),
        ('{"terms": [{"variance_mm2": -1, "weights": [1, 1, 1]}]}', "finite and > 0"),
        ('{"terms": [{"variance_mm2": 1, "weights": [0.5, 1, 1]}]}', "sum to 1"),
        ('{"terms": [{"weights": [1, 1, 1]}]}', "not a fit document"),
    ],
)
def test_bad_fit_json(tmp_path: Path, content: str, message: str) -> None:
    path = tmp_path / "f.json"
    path.write_text(content)
    with pytest.raises(InputError, match=message):
        read_fit_json(path)
