"""Read and write measured profiles (CSV) and fits (JSON) at the stage boundaries."""

from __future__ import annotations

import csv
import io
import json
import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from ..fileio import atomic_write_json, atomic_write_text
from .types import FitResult, MeasuredProfile, fit_result_from_json

PROFILE_COLUMNS = ("radius_mm", "R", "G", "B")
STDDEV_COLUMNS = ("std_R", "std_G", "std_B")


MAX_PROFILE_ROWS = 100_000
"""More samples than this are refused: a radial profile at one sample per pixel ring of a
4000-pixel capture has 2000, and the fit's cost grows with the rows."""


def read_profile_csv(path: str | Path, name: str | None = None) -> MeasuredProfile:
    """Read PROFILE.csv: a header, then ``radius_mm,R,G,B`` and optional ``std_R,std_G,std_B``.

    Values may be ``nan``/``inf`` (the fit drops such rows with a warning); anything
    that is not a number is an :class:`InputError` naming the row and column, and so is
    a negative value beyond three standard deviations (or any, without them): a
    profile is a radiance. The body is parsed by numpy (2 M rows in about 1 s) and
    refused beyond :data:`MAX_PROFILE_ROWS` rows.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError("no such file", path)
    size = path.stat().st_size
    if size > MAX_PROFILE_ROWS * 200:  # count, don't parse: a row is about 60 bytes
        with open(path, "rb") as handle:
            rows = sum(chunk.count(b"\n") for chunk in iter(lambda: handle.read(1 << 24), b""))
        raise InputError(f"{rows} rows ({size / 1e6:.0f} MB): more than {MAX_PROFILE_ROWS} "
                         "rows is not a radial profile (resample it)", path)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError:
        raise InputError("not a CSV text file (binary or not UTF-8): a profile is text "
                         f"with a header {','.join(PROFILE_COLUMNS)}", path) from None
    except OSError as exc:
        raise InputError(f"cannot read: {exc.strerror or exc}", path) from exc
    lines = text.splitlines()
    first = next((i for i, line in enumerate(lines) if line.strip(", \t")), None)
    if first is None:
        raise InputError("empty file: expected a header radius_mm,R,G,B", path)
    header = [h.strip() for h in next(csv.reader([lines[first]]))]
    missing = [c for c in PROFILE_COLUMNS if c not in header]
    if missing:
        raise InputError(
            f"missing column(s) {', '.join(missing)} in header {','.join(header)!r} "
            f"(expected {','.join(PROFILE_COLUMNS)}[,{','.join(STDDEV_COLUMNS)}])",
            path,
        )
    body = [(i, line) for i, line in enumerate(lines[first + 1:], start=first + 2)
            if line.strip(", \t")]
    if len(body) > MAX_PROFILE_ROWS:
        raise InputError(f"{len(body)} samples: more than {MAX_PROFILE_ROWS} rows is not a "
                         "radial profile (resample it)", path)
    if not body:
        raise InputError("header only: no samples", path)
    ragged = next(((n, line) for n, line in body
                   if line.count(",") > len(header) - 1), None)
    if ragged is not None:
        raise InputError(f"line {ragged[0]}: {ragged[1].count(',') + 1} cells, more than "
                         f"the header's {len(header)}", path)
    has_std = all(c in header for c in STDDEV_COLUMNS)
    wanted = PROFILE_COLUMNS + (STDDEV_COLUMNS if has_std else ())
    index = [header.index(c) for c in wanted]
    data = _parse_rows(path, body, index, wanted)
    values, std = data[:, 1:4], data[:, 4:7] if has_std else None
    negative = values < (-3.0 * np.nan_to_num(std, nan=0.0) if std is not None else 0.0)
    if negative.any():
        row, col = (int(v) for v in np.argwhere(negative)[0])
        raise InputError(f"line {body[row][0]}, column {'RGB'[col]}: {values[row, col]:.6g} is "
                         "negative (beyond 3 standard deviations): a profile is a radiance",
                         path)
    return MeasuredProfile(radius_mm=data[:, 0], values=values, stddev=std,
                           name=name or path.stem, source=path)


def _parse_rows(path: Path, body: list[tuple[int, str]], index: list[int],
                wanted: tuple[str, ...]) -> np.ndarray:
    """The ``index`` columns of ``body`` as floats: numpy's parser, and on failure the
    row-by-row reading that names the line and column at fault."""
    try:
        data = np.loadtxt(io.StringIO("\n".join(line for _, line in body)), delimiter=",",
                          usecols=index, ndmin=2, dtype=np.float64, comments=None)
        if data.shape == (len(body), len(index)):
            return data
    except ValueError:
        pass
    data = np.empty((len(body), len(index)))
    for r, (number, line) in enumerate(body):
        row = next(csv.reader([line]))
        for j, col in enumerate(index):
            try:
                data[r, j] = float(row[col])
            except (IndexError, ValueError):
                cell = row[col] if col < len(row) else "<missing>"
                raise InputError(
                    f"line {number}, column {wanted[j]}: {cell!r} is not a number", path
                ) from None
    return data


def write_profile_csv(path: str | Path, profile: MeasuredProfile) -> Path:
    """Write a profile in the PROFILE.csv format (atomically)."""
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    std = profile.stddev
    writer.writerow(PROFILE_COLUMNS + (STDDEV_COLUMNS if std is not None else ()))
    for i, r in enumerate(profile.radius_mm):
        row = [r, *profile.values[i]] + ([*std[i]] if std is not None else [])
        writer.writerow([f"{float(x):.9g}" for x in row])
    return atomic_write_text(path, out.getvalue())


def write_fit_json(path: str | Path, fit: FitResult) -> Path:
    """Write FIT.json (atomically); its ``source`` relative to the file's folder, so that
    a folder of outputs moved or written elsewhere holds the same bytes."""
    doc = fit.to_json()
    if doc.get("source") and Path(doc["source"]).is_absolute():
        doc["source"] = os.path.relpath(doc["source"], Path(path).resolve().parent)
    return atomic_write_json(path, doc)


def read_fit_json(path: str | Path) -> FitResult:
    """Read FIT.json; :class:`InputError` names the file if it is not a valid fit."""
    path = Path(path)
    if not path.is_file():
        raise InputError("no such file", path)
    try:
        doc: Any = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"not valid JSON: {exc}", path) from exc
    if not isinstance(doc, dict):
        raise InputError("a fit document must be a JSON object", path)
    try:
        fit = fit_result_from_json(doc, name=str(doc.get("name") or path.stem))
    except InputError as exc:
        raise InputError(str(exc), path) from exc
    _check_fit(fit, path)
    if fit.source and not Path(fit.source).is_absolute():
        fit.source = str((path.parent / fit.source).resolve())
    return fit


def _check_fit(fit: FitResult, path: Path) -> None:
    if fit.variances_mm2.size == 0:
        raise InputError("the fit has no terms", path)
    if not np.all(np.isfinite(fit.variances_mm2)) or np.any(fit.variances_mm2 <= 0):
        raise InputError(f"variances must be finite and > 0 mm^2: {fit.variances_mm2}", path)
    if not np.all(np.isfinite(fit.weights)) or np.any(fit.weights < 0):
        raise InputError("weights must be finite and >= 0", path)
    sums = fit.weights.sum(axis=0)
    if not all(math.isclose(s, 1.0, abs_tol=1e-4) for s in sums):
        raise InputError(f"weights must sum to 1 per channel, got {np.round(sums, 6)}", path)


def read_fit_inputs(paths: Sequence[str | Path]) -> list[FitResult]:
    """Fits from JSON files and/or directories of ``*.json`` (sorted by name)."""
    files: list[Path] = []
    for p in map(Path, paths):
        if p.is_dir():
            found = sorted(q for q in p.glob("*.json") if not q.name.startswith("."))
            if not found:
                raise InputError("no *.json fit files in this directory", p)
            files.extend(found)
        else:
            files.append(p)
    return [read_fit_json(f) for f in files]
