"""The command line: exit codes, outputs, nothing written on bad input."""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from skinpipe.cli import build_parser, main
from skinpipe.profile.io import write_profile_csv

from ..reference_profiles import deon_profile, dipole_normalised


def test_help_lists_verbs(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--help"]) == 0
    out = capsys.readouterr().out
    assert "fit" in out and "Exit codes" in out


def test_fit_help_gives_units(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["fit", "--help"]) == 0
    out = capsys.readouterr().out
    assert "mm^2" in out and "--share" in out


def test_every_option_states_its_default_once(capsys: pytest.CaptureFixture[str]) -> None:
    """Against argparse's plain formatter: an option whose help states its default is
    shown as written; one with a default to show (not None, False or empty) and no word
    of it gets argparse's "(default: X)", a list or tuple as the option's own type reads it
back ("512,1024", "1:8", not "[512, 1024]"); none ever shows "(default: None)"."""
    parser = build_parser()
    verbs = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    checked = appended = listed = 0
    for verb, sub in verbs.choices.items():
        ours = sub._get_formatter()
        plain = argparse.HelpFormatter(sub.prog)
        for action in sub._actions:
            if action.help in (None, argparse.SUPPRESS) or not action.option_strings:
                continue
            shown = " ".join(ours._expand_help(action).split())
            written = " ".join(plain._expand_help(action).split())
            where = f"{verb} {action.option_strings[-1]}: {shown!r}"
            default = action.default
            nothing = default is None or default is False or default == argparse.SUPPRESS \
                or (isinstance(default, (str, tuple, list)) and not default)
            if nothing or "default" in written.lower():
                assert shown == written, where
            elif isinstance(default, (list, tuple)):
                # as the user would type it: the option's own type reads it back
                typed = shown.rsplit("(default: ", 1)[1][:-1]
                assert shown == f"{written} (default: {typed})", where
                assert action.type(typed) == default, where
                listed += 1
            else:
                assert shown == f"{written} (default: {default})", where
                appended += 1
            assert "(default: None)" not in shown, where
            checked += 1
    assert checked > 100 and appended > 20 and listed >= 6
    assert main(["render", "--help"]) == 0
    out = " ".join(capsys.readouterr().out.split())
    assert "(default: the first camera on the stage)" in out and "(default: None)" not in out


def test_fit_writes_the_documented_json(tmp_path: Path) -> None:
    csv = write_profile_csv(tmp_path / "forehead.csv", deon_profile())
    out = tmp_path / "fit.json"
    assert main(["fit", str(csv), "-k", "6", "--share", "channels", "--seed", "1",
                 "-o", str(out)]) == 0
    doc = json.loads(out.read_text())
    assert len(doc["terms"]) == 6
    assert set(doc["terms"][0]) == {"variance_mm2", "weights"}
    # point samples of d'Eon's sum: the energy term reads them as ring means, O(dr^2)
    # off, so the values' eq. 2c is no longer exactly zero at the optimum
    assert len(doc["error"]) == 3 and max(doc["error"]) < 2e-3
    assert set(doc["edge"]) == {"edge_error", "edge_width_mm", "edge_width_measured_mm",
                                "shadow_light_ratio"}
    assert max(doc["edge"]["edge_error"]) < 0.01
    assert doc["status"] == "Solve_Succeeded"
    assert doc["units"] == {"radius": "mm", "variance": "mm^2"}
    # the fit's content only: no run facts, its source relative to it, so the same
    # profile and options give the same bytes
    assert "seconds" not in doc and doc["source"] == "forehead.csv"
    again = tmp_path / "again.json"
    assert main(["fit", str(csv), "-k", "6", "--share", "channels", "--seed", "1",
                 "-o", str(again)]) == 0
    assert again.read_bytes() == out.read_bytes()


def test_fit_several_profiles_share_one_grid(tmp_path: Path) -> None:
    a = write_profile_csv(tmp_path / "cheek.csv", dipole_normalised("skin1"))
    b = write_profile_csv(tmp_path / "nose.csv", dipole_normalised("skin2"))
    out = tmp_path / "fits"
    assert main(["fit", str(a), str(b), "-k", "4", "--share", "profiles", "-o", str(out)]) == 0
    docs = [json.loads((out / f"{n}.json").read_text()) for n in ("cheek", "nose")]
    assert [t["variance_mm2"] for t in docs[0]["terms"]] == \
        [t["variance_mm2"] for t in docs[1]["terms"]]


def test_bad_input_exit_2_and_nothing_written(tmp_path: Path,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "bad.csv"
    bad.write_text("radius_mm,R,G,B\n0,0,0,0\n0.1,0,0,0\n")
    out = tmp_path / "fit.json"
    assert main(["fit", str(bad), "-k", "1", "-o", str(out)]) == 2
    assert not out.exists()
    assert list(tmp_path.iterdir()) == [bad]
    assert "bad.csv" in capsys.readouterr().err


def test_usage_error_exit_2() -> None:
    assert main(["fit"]) == 2


def test_console_script_runs() -> None:
    proc = subprocess.run([sys.executable, "-m", "skinpipe", "--version"],
                          capture_output=True, text=True, check=False)
    assert proc.returncode == 0 and "skinpipe" in proc.stdout


def test_demo_on_sample_assets(demo_run: tuple[Path, str, str]) -> None:
    """The README's first command, at its defaults (shared with the other tests that
    read the demo's outputs)."""
    out, stdout, stderr = demo_run
    report = json.loads((out / "report.json").read_text())
    render = json.loads((out / "render" / "render.json").read_text())["frames"][0]
    assert len(render["measures"]["diffusion"]["grid_error_eq2c"]) == 6  # six profiles
    assert abs(render["measures"]["diffusion"]["energy_ratio"] - 1) < 5e-3
    for png in ("Face.png", "figure7_texture_vs_scattering.png",
                "per_region_vs_one_profile.png"):
        assert (out / "render" / png).is_file(), png
    # the one-profile render reuses the irradiance and the seam layout (the texture-only
    # render between them has no layout of its own)
    assert set(report["comparisons"]["one_profile"]["cached"]) >= {"irradiance",
                                                                   "diffusion_layout"}
    assert sorted(report["regions"]) == sorted(
        ["forehead", "lips", "chin", "cheekbone", "cheek", "nose"])
    for name, entry in report["regions"].items():
        assert max(entry["error_vs_truth"]) < 0.03, name
        assert (out / "fits" / f"{name}.json").is_file()
        assert (out / "profiles" / f"{name}.exr").is_file()
    assert "[6/6]" in stderr  # progress on stderr
    assert "forehead" in stdout


def test_the_demo_head_has_no_holes(demo_run: tuple[Path, str, str]) -> None:
    """The camera never sees the background through the scan: no transparent pixel
    inside the head's outline (its coverage closed over cracks up to 16 px wide), where
    the scan's cracks along the jaws and the ear showed 2,524 with the seal hidden."""
    import OpenImageIO as oiio
    from scipy.ndimage import binary_closing, binary_fill_holes

    buf = oiio.ImageBuf(str(demo_run[0] / "render" / "Face.exr"))
    alpha = np.asarray(buf.get_pixels(oiio.FLOAT))[..., list(buf.spec().channelnames).index("A")]
    yy, xx = np.mgrid[-8:9, -8:9]
    head = np.pad(alpha > 0.5, 10)
    outline = binary_fill_holes(binary_closing(head, (xx**2 + yy**2) <= 64))[10:-10, 10:-10]
    assert int((outline & (alpha < 0.01)).sum()) == 0


def test_the_demo_has_no_negative_light(demo_run: tuple[Path, str, str]) -> None:
    """No AOV of the demo render holds light below zero (the recursive blur's ringing
    left the diffuse at -1.4e-4 on unlit skin)."""
    import OpenImageIO as oiio

    buf = oiio.ImageBuf(str(demo_run[0] / "render" / "Face.exr"))
    pixels = np.asarray(buf.get_pixels(oiio.FLOAT))
    lowest = pixels.reshape(-1, pixels.shape[-1]).min(axis=0)
    assert float(lowest.min()) >= 0.0, dict(zip(buf.spec().channelnames, lowest, strict=True))


def test_ingest_then_fit_through_the_cli(tmp_path: Path) -> None:
    captures = Path(__file__).parents[2] / "skinpipe" / "samples" / "captures"
    assert main(["ingest", str(captures), "--regions", "cheek", "-o", str(tmp_path)]) == 0
    assert main(["fit", str(tmp_path / "cheek.csv"), "-k", "4", "--free-scale",
                 "-o", str(tmp_path / "cheek.json")]) == 0
    doc = json.loads((tmp_path / "cheek.json").read_text())
    assert max(doc["error"]) < 0.01 and len(doc["total_reflectance"]) == 3


def test_the_progress_bar_in_a_log(capsys: pytest.CaptureFixture[str]) -> None:
    """Not a terminal: one line per task with the share done rising, other messages as
    they are, a finished bar's total; a failed one ends without it."""
    from skinpipe.cli.common import TaskBar

    shares = {"irradiance": 0.5, "diffusion": 0.3, "shade": 0.2}
    with TaskBar(shares) as bar:
        for message in ("irradiance", "unwrap /Mesh with xatlas", "diffusion", "shade"):
            bar(message)
    lines = capsys.readouterr().err.strip().splitlines()
    shares_seen = [int(line.split("%")[0].split()[-1]) for line in lines if "%" in line]
    assert shares_seen == [0, 50, 80, 100] and "unwrap /Mesh with xatlas" in lines
    assert lines[-1].startswith("[" + "#" * 24 + "] 100% done")
    with pytest.raises(RuntimeError), TaskBar(shares) as bar:
        bar("irradiance")
        raise RuntimeError("stop")
    assert "done" not in capsys.readouterr().err


def test_interleave_period_is_auto_or_a_period(capsys: pytest.CaptureFixture[str]) -> None:
    """--interleave-period: 'auto' (the default) is the options' 0; 2, 4 or 8 as given;
    anything else an argparse error naming the choices."""
    import argparse

    from skinpipe.cli.common import add_render_options, render_options

    parser = argparse.ArgumentParser()
    add_render_options(parser)
    assert render_options(parser.parse_args([])).interleave_period == 0
    assert render_options(parser.parse_args(["--interleave-period", "AUTO"])
                          ).interleave_period == 0
    assert render_options(parser.parse_args(["--interleave-period", "4"])
                          ).interleave_period == 4
    for bad in ("3", "16", "four"):
        with pytest.raises(SystemExit):
            parser.parse_args(["--interleave-period", bad])
        assert "expected auto or one of 2, 4, 8" in capsys.readouterr().err
