"""Ingest stage: simulate -> ingest -> fit recovers the truth; bad input fails cleanly."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import OpenImageIO as oiio
import pytest

from skinpipe.capture.ingest import IngestOptions, ingest_capture_set, read_capture_set
from skinpipe.capture.simulate import (
    PRESETS,
    CaptureSettings,
    read_truth,
    sample_subject_truths,
    simulate_capture_set,
)
from skinpipe.cli import main
from skinpipe.errors import InputError
from skinpipe.imageio import write_exr
from skinpipe.profile.fit import fit_sum_of_gaussians
from skinpipe.profile.io import read_profile_csv

TRUTHS = {t.name: t for t in sample_subject_truths()}


def run_chain(tmp: Path, regions: list[str], settings: CaptureSettings, seed: int) -> dict:
    caps = tmp / f"caps{seed}"
    simulate_capture_set([TRUTHS[r] for r in regions], caps, settings, seed=seed)
    report = ingest_capture_set(caps, tmp / f"out{seed}")
    truth_doc = json.loads((caps / "truth.json").read_text())
    observed = read_truth(caps / "truth.json")  # with the projector's footprint
    results = {}
    for name in regions:
        prof = read_profile_csv(report["regions"][name]["csv"])
        fit = fit_sum_of_gaussians(prof, k=6, free_scale=True, seed=seed)
        r = prof.radius_mm
        entry = np.array(report["regions"][name]["entry_point_px"])
        true_entry = truth_doc["regions"][name]["entry_point_px"]
        results[name] = {
            "fit_error": observed[name].profile_error(r, fit.evaluate(r)),
            "raw_error": observed[name].profile_error(r, prof.values),
            "entry_error_px": float(np.hypot(*(entry - true_entry))),
        }
    return results


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_simulate_ingest_fit_recovers_truth(tmp_path: Path, seed: int) -> None:
    res = run_chain(tmp_path, ["forehead", "cheek"], CaptureSettings(), seed)
    for name, r in res.items():
        assert r["fit_error"].max() < 0.03, (name, r)
        assert r["entry_error_px"] < 0.25, (name, r)


@pytest.mark.parametrize("seed", [4, 5])
def test_hair_strands_across_the_spot(tmp_path: Path, seed: int) -> None:
    res = run_chain(tmp_path, ["lips", "chin"], CaptureSettings(hair_strands=3), seed)
    for name, r in res.items():
        assert r["fit_error"].max() < 0.05, (name, r)
        assert r["entry_error_px"] < 0.25, (name, r)


def test_eight_bit_srgb_captures(tmp_path: Path) -> None:
    settings = CaptureSettings(bits=8, image_format="png",
                               exposures_s=tuple(1 / 500 * 4.0**i for i in range(7)))
    res = run_chain(tmp_path, ["nose"], settings, seed=7)
    assert res["nose"]["fit_error"].max() < 0.03
    assert res["nose"]["entry_error_px"] < 0.25


def test_median_rings_beat_the_cross_section_under_hair(tmp_path: Path) -> None:
    caps = tmp_path / "caps"
    simulate_capture_set([TRUTHS["cheek"]], caps, CaptureSettings(hair_strands=4), seed=11)
    errors = {}
    for mode in ("rings", "cross_section"):
        report = ingest_capture_set(caps, tmp_path / mode, IngestOptions(mode=mode))
        prof = read_profile_csv(report["regions"]["cheek"]["csv"])
        errors[mode] = TRUTHS["cheek"].profile_error(prof.radius_mm, prof.values,
                                                     hi_mm=3.9).max()
    assert errors["rings"] < errors["cross_section"]


def test_exposure_from_exif(tmp_path: Path) -> None:
    caps = tmp_path / "caps"
    simulate_capture_set([TRUTHS["nose"]], caps,
                         CaptureSettings(size_px=96, exposure_in_manifest=False), seed=0)
    doc = json.loads((caps / "capture.json").read_text())
    assert "exposure_s" not in doc["regions"]["nose"]["images"][0]
    report = ingest_capture_set(caps, tmp_path / "out")
    assert report["regions"]["nose"]["brackets"] == 5


# ------------------------------------------------------------------------- bad input


@pytest.fixture(scope="module")
def small_capture(tmp_path_factory: pytest.TempPathFactory) -> Path:
    caps = tmp_path_factory.mktemp("small") / "caps"
    simulate_capture_set([TRUTHS["forehead"], TRUTHS["cheek"]], caps,
                         CaptureSettings(size_px=96, exposures_s=(1 / 500, 1 / 60, 1 / 8)),
                         seed=3)
    return caps


def _copy(src: Path, tmp: Path) -> Path:
    dst = tmp / "caps"
    shutil.copytree(src, dst)
    return dst


def _manifest(caps: Path) -> dict:
    return json.loads((caps / "capture.json").read_text())


def _save(caps: Path, doc: dict) -> None:
    (caps / "capture.json").write_text(json.dumps(doc))


def _break_missing(caps: Path) -> str:
    (caps / "cheek" / "e1.tif").unlink()
    return "e1.tif"


def _break_empty(caps: Path) -> str:
    (caps / "cheek" / "e1.tif").write_bytes(b"")
    return "e1.tif"


def _break_truncated(caps: Path) -> str:
    path = caps / "cheek" / "e2.tif"
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 3])
    return "e2.tif"


def _break_garbage(caps: Path) -> str:
    (caps / "cheek" / "e0.tif").write_bytes(b"not an image at all" * 50)
    return "e0.tif"


def _break_png_named_exr(caps: Path) -> str:
    buf = oiio.ImageBuf(oiio.ImageSpec(96, 96, 3, "uint8"))
    buf.write(str(caps / "cheek" / "fake.png"))
    (caps / "cheek" / "fake.png").rename(caps / "cheek" / "e0.exr")
    doc = _manifest(caps)
    doc["regions"]["cheek"]["images"][0]["file"] = "cheek/e0.exr"
    _save(caps, doc)
    return "e0.exr"


def _break_sizes(caps: Path) -> str:
    buf = oiio.ImageBuf(str(caps / "cheek" / "e1.tif"))
    small = oiio.ImageBufAlgo.cut(buf, oiio.ROI(0, 80, 0, 80))
    small.write(str(caps / "cheek" / "e1.tif"))
    return "differ in size"


def _break_no_exposure(caps: Path) -> str:
    buf = oiio.ImageBuf(str(caps / "cheek" / "e1.tif"))
    pixels = buf.get_pixels(oiio.UINT16)
    out = oiio.ImageBuf(oiio.ImageSpec(96, 96, 3, "uint16"))
    out.set_pixels(oiio.ROI(0, 96, 0, 96), pixels)
    out.write(str(caps / "cheek" / "e1.tif"))  # no EXIF
    doc = _manifest(caps)
    for img in doc["regions"]["cheek"]["images"]:
        img.pop("exposure_s")
    _save(caps, doc)
    return "no exposure time"


def _rewrite_all(caps: Path, value: int) -> None:
    for f in (caps / "cheek").glob("*.tif"):
        out = oiio.ImageBuf(oiio.ImageSpec(96, 96, 3, "uint16"))
        out.set_pixels(oiio.ROI(0, 96, 0, 96), np.full((96, 96, 3), value, np.uint16))
        out.specmod().attribute("ExposureTime", 0.01)
        out.write(str(f))


def _break_all_clipped(caps: Path) -> str:
    _rewrite_all(caps, 65535)
    return "clipped"


def _break_all_black(caps: Path) -> str:
    _rewrite_all(caps, 0)
    return "black"


def _break_nan_exr(caps: Path) -> str:
    img = np.full((96, 96, 3), 0.5, np.float32)
    img[10, 10, 1] = np.nan
    write_exr(caps / "cheek" / "e0.exr", img, "lin_rec709_scene")
    doc = _manifest(caps)
    doc["regions"]["cheek"]["images"][0]["file"] = "cheek/e0.exr"
    _save(caps, doc)
    return "non-finite"


def _break_json(caps: Path) -> str:
    (caps / "capture.json").write_text("{not json")
    return "not valid JSON"


def _break_missing_key(caps: Path) -> str:
    doc = _manifest(caps)
    del doc["mm_per_pixel"]
    _save(caps, doc)
    return "missing key 'mm_per_pixel'"


def _break_colorspace(caps: Path) -> str:
    doc = _manifest(caps)
    doc["camera_colorspace"] = "not_a_colourspace"
    _save(caps, doc)
    return "unknown OCIO colour space"


def _break_single_clipped(caps: Path) -> str:
    _rewrite_all(caps, 65535)
    doc = _manifest(caps)
    doc["regions"]["cheek"]["images"] = doc["regions"]["cheek"]["images"][:1]
    _save(caps, doc)
    return "clipped"


BREAKERS = [_break_missing, _break_empty, _break_truncated, _break_garbage, _break_png_named_exr,
            _break_sizes, _break_no_exposure, _break_all_clipped, _break_all_black,
            _break_nan_exr, _break_json, _break_missing_key, _break_colorspace,
            _break_single_clipped]


@pytest.mark.parametrize("breaker", BREAKERS, ids=lambda f: f.__name__[7:])
def test_bad_input_exit_2_names_file_writes_nothing(
    small_capture: Path, tmp_path: Path, breaker, capsys: pytest.CaptureFixture[str]
) -> None:
    caps = _copy(small_capture, tmp_path)
    expected = breaker(caps)
    out = tmp_path / "out"
    assert main(["ingest", str(caps), "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert expected in err, err
    assert str(caps) in err, err
    assert not out.exists()


def test_one_unclipped_bracket_is_allowed_with_a_warning(small_capture: Path,
                                                          tmp_path: Path) -> None:
    caps = _copy(small_capture, tmp_path)
    doc = _manifest(caps)
    for region in doc["regions"].values():
        region["images"] = region["images"][:1]
    _save(caps, doc)
    notes: list[str] = []
    report = ingest_capture_set(caps, tmp_path / "out", progress=notes.append)
    assert report["regions"]["cheek"]["brackets"] == 1
    assert any("one bracket only" in n for n in notes)


def test_manifest_reader_rejects_bad_exposure(small_capture: Path, tmp_path: Path) -> None:
    caps = _copy(small_capture, tmp_path)
    doc = _manifest(caps)
    doc["regions"]["cheek"]["images"][0]["exposure_s"] = -1
    _save(caps, doc)
    with pytest.raises(InputError, match="exposure_s must be > 0"):
        read_capture_set(caps)


def test_sample_assets_truth_matches_the_simulator() -> None:
    from dataclasses import replace

    samples = Path(__file__).parents[2] / "skinpipe" / "samples"
    truth = read_truth(samples / "captures" / "truth.json")
    assert sorted(truth) == sorted(TRUTHS)
    r = np.linspace(0, 4, 50)
    for name, t in truth.items():
        assert t.footprint_sigma_mm == PRESETS["realistic"].footprint_sigma_mm
        np.testing.assert_allclose(t.acescg_profile(r), replace(
            TRUTHS[name], footprint_sigma_mm=t.footprint_sigma_mm).acescg_profile(r))


def test_ingest_states_an_honest_uncertainty(tmp_path: Path) -> None:
    """Issue 20: ingest.json's expected eq. 2c error of the profile's shape (from the
    per-sample standard errors: ring statistics, floored by the sensor's noise model) is
    neither overconfident nor loose against the sample captures' known truth over the
    measured disk: within 0.5-3x of the actual error in every channel of every region
    (measured: 0.73-1.73x, the forehead 1.9-2.4x). The scale (the tail beyond the image)
    is stated apart: the truth's share beyond the image within the stated uncertainty
    on every channel of every region."""
    from skinpipe.capture.ingest import ingest_capture_set
    from skinpipe.capture.simulate import read_truth
    from skinpipe.profile.io import read_profile_csv

    captures = Path(__file__).parents[2] / "skinpipe" / "samples" / "captures"
    truth = read_truth(captures / "truth.json")
    report = ingest_capture_set(captures, tmp_path)
    for name, entry in report["regions"].items():
        prof = read_profile_csv(entry["csv"])
        actual = truth[name].profile_error(prof.radius_mm, prof.values, over="disk")
        ratio = np.asarray(entry["expected_error_eq2c"]) / actual
        assert np.all((ratio > 0.5) & (ratio < 3.0)), (name, ratio)
        tail = entry["tail_beyond_image"]
        true_share = truth[name].share_beyond_mm(float(prof.radius_mm[-1]
                                                       + 0.5 * np.diff(prof.radius_mm)[-1]))
        assert np.all(np.abs(np.asarray(tail["fraction_of_flux"]) - true_share)
                      <= np.asarray(tail["scale_uncertainty"]) + 1e-3), (name, tail, true_share)
        assert entry["sensor_noise"]["source"] == "estimated"


def _draw_strand(captures: Path, region: str, offset_px: float, angle: float) -> None:
    """A dark strand drawn into every bracket of ``region`` here (numpy, not skinpipe's
    simulator): 2.5 px wide, passing 20% of the light (not of the sensor's offset, the
    black level in truth.json's settings), ``offset_px`` from the centre."""
    import OpenImageIO as oiio

    black = json.loads((captures / "truth.json").read_text())["regions"][region][
        "settings"]["black_level"]
    paths = sorted((captures / region).glob("*.tif"))
    first = np.asarray(oiio.ImageBuf(str(paths[0])).get_pixels(oiio.FLOAT)).sum(axis=2)
    cy, cx = np.unravel_index(int(np.argmax(first)), first.shape)  # the shortest: unclipped
    for path in paths:
        buf = oiio.ImageBuf(str(path))
        spec = buf.spec()
        px = np.asarray(buf.get_pixels(oiio.FLOAT))
        h, w = px.shape[:2]
        yy, xx = np.mgrid[0:h, 0:w]
        d = np.abs((xx - cx) * -math.sin(angle) + (yy - cy) * math.cos(angle) - offset_px)
        cover = np.clip(1.0 - (d - 1.25), 0.0, 1.0)
        px = black + (px - black) * (1.0 - 0.8 * cover)[..., None]
        out = oiio.ImageBuf(oiio.ImageSpec(w, h, px.shape[2], oiio.UINT16))
        out.set_pixels(oiio.ROI(), px.astype(np.float32))
        for attr in spec.extra_attribs:
            out.specmod().attribute(attr.name, attr.type, attr.value)
        assert out.write(str(path))


def test_hair_beside_the_entry_point_is_masked_and_over_it_refused(tmp_path: Path) -> None:
    """Issue 20: strands drawn by this test 7 and 12 px from the entry point are found
    as outliers against the radial model and masked (eq. 2c against the truth: 0.22%,
    0.34% without the mask, 0.20% without the strands); a strand through the entry
    point is a clear refusal naming the region. (A strand 4 px away still pulls the
    entry point 2.6 px and the profile to 1-3%: not solved.)"""
    from skinpipe.capture.ingest import ingest_capture_set
    from skinpipe.capture.simulate import read_truth
    from skinpipe.errors import SkinpipeError
    from skinpipe.profile.io import read_profile_csv

    truths = [t for t in sample_subject_truths() if t.name == "cheek"]
    caps = tmp_path / "caps"
    simulate_capture_set(truths, caps, PRESETS["legacy"], seed=5)  # the measured setup
    for offset, angle in ((-7.0, 1.2), (12.0, 2.0)):
        _draw_strand(caps, "cheek", offset, angle)
    report = ingest_capture_set(caps, tmp_path / "out")
    entry = report["regions"]["cheek"]
    assert any("hair masked" in w for w in entry["warnings"])
    prof = read_profile_csv(entry["csv"])
    truth = read_truth(caps / "truth.json")["cheek"]
    # the profile's shape (over the measured disk): the tail's extrapolation, which
    # scales the whole profile by 1-2% here, is not what hair changes
    assert truth.profile_error(prof.radius_mm, prof.values, over="disk").max() < 0.003
    _draw_strand(caps, "cheek", 0.0, 0.7)
    with pytest.raises(SkinpipeError, match="'cheek': hair covers"):
        ingest_capture_set(caps, tmp_path / "out2")


def test_the_manifest_sensor_and_its_black_level(tmp_path: Path) -> None:
    """capture.json's sensor: a black level given there is used as it is (the brackets
    still give the gain and read noise they are not told); bad values are refused with
    the key named."""
    caps = tmp_path / "caps"
    simulate_capture_set([TRUTHS["nose"]], caps, CaptureSettings(size_px=96), seed=2)
    doc = json.loads((caps / "capture.json").read_text())
    doc["sensor"] = {"full_well_e": 20000, "read_noise_e": 4, "black_level": 2048 / 65535}
    (caps / "capture.json").write_text(json.dumps(doc))
    report = ingest_capture_set(caps, tmp_path / "out")
    noise = report["regions"]["nose"]["sensor_noise"]
    assert noise["black_level_source"] == "manifest" and noise["source"] == "manifest"
    assert noise["black_level_code"] == pytest.approx(2048 / 65535)
    for bad, key in (({"full_well_e": 20000, "read_noise_e": 4, "black_level": 0.7},
                      "black_level"),
                     ({"full_well_e": 20000, "read_noise_e": 4, "black_level": "low"},
                      "black_level"),
                     ({"read_noise_e": 4}, "'sensor' must be"),
                     ({"full_well_e": -1, "read_noise_e": 4}, "full_well_e")):
        doc["sensor"] = bad
        (caps / "capture.json").write_text(json.dumps(doc))
        with pytest.raises(InputError, match=key):
            read_capture_set(caps)


def test_regions_ingested_side_by_side_equal_each_region_alone(small_capture: Path,
                                                               tmp_path: Path) -> None:
    """The capture set's regions run on threads side by side: each region's profile and
    merged HDR are the same, bit for bit, as ingesting it alone, in the manifest's order;
    and a region that fails fails the set, which writes nothing."""
    from skinpipe.capture.ingest import ingest_region
    from skinpipe.imageio import read_image
    from skinpipe.profile.io import write_profile_csv

    report = ingest_capture_set(small_capture, tmp_path / "out")
    captures = read_capture_set(small_capture)
    assert list(report["regions"]) == list(captures.regions)
    for name in captures.regions:
        alone = ingest_region(captures, name)
        csv = write_profile_csv(tmp_path / f"{name}_alone.csv", alone.profile)
        assert Path(report["regions"][name]["csv"]).read_bytes() == csv.read_bytes()
        np.testing.assert_array_equal(read_image(report["regions"][name]["exr"]).pixels,
                                      alone.hdr.astype(np.float32))
    caps = _copy(small_capture, tmp_path)
    doc = _manifest(caps)
    (caps / doc["regions"]["forehead"]["images"][1]["file"]).write_bytes(b"not an image")
    with pytest.raises(InputError):
        ingest_capture_set(caps, tmp_path / "bad")
    assert not (tmp_path / "bad").exists() or not any((tmp_path / "bad").iterdir())


def test_a_sharp_entry_spike_is_light_not_hair(tmp_path: Path) -> None:
    """A pencil capture of the light tracer's skin1 (22 / 37 / 52% of its light within
    0.025 mm: single scattering), no footprint: the ingest takes the spike for light,
    not a strand, and keeps its energy (the light within 0.1 mm against that within
    2 mm as the traced profile has it, within 5%: measured 2-3.5% over, the core
    model's Gaussians no narrower than 0.35 px); a strand drawn through the entry point
    is still refused."""
    from skinpipe.capture.simulate import ring_truth
    from skinpipe.errors import SkinpipeError
    from skinpipe.profile.models import ring_edges_mm

    truth = ring_truth(Path(__file__).parents[1] / "fixtures" / "physics" / "skin1.csv")
    caps = tmp_path / "caps"
    settings = CaptureSettings(footprint_sigma_mm=0.0, size_px=400,
                               camera_colorspace="lin_ap1_scene")
    simulate_capture_set([truth], caps, settings, seed=3)
    report = ingest_capture_set(caps, tmp_path / "out")
    prof = read_profile_csv(report["regions"]["skin1"]["csv"])

    def within(radius_mm: np.ndarray, values: np.ndarray, edge_mm: float) -> np.ndarray:
        outer = ring_edges_mm(radius_mm)  # each ring's outer edge
        inner = np.concatenate([[0.0], outer[:-1]])
        area = np.pi * np.clip(np.minimum(outer, edge_mm) ** 2 - inner**2, 0.0, None)
        return (values * area[:, None]).sum(axis=0)

    rings, values = np.asarray(truth.ring_radius_mm), np.asarray(truth.ring_values)
    # the share of each profile's own measured light (the scale over the plane, tail
    # extrapolation included, is the fit's free scale's to settle)
    reach = 2.0  # both against the light within 2 mm, which every pixel there resolves
    want = within(rings, values, 0.1) / within(rings, values, reach)
    got = within(prof.radius_mm, prof.values, 0.1) / within(prof.radius_mm, prof.values, reach)
    assert np.all(np.abs(got / want - 1) < 0.05), (got, want)
    _draw_strand(caps, "skin1", 0.0, 0.7)
    with pytest.raises(SkinpipeError, match="'skin1': hair covers"):
        ingest_capture_set(caps, tmp_path / "out2")
