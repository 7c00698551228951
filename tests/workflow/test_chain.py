"""The demo chain (skinpipe/workflow/chain.py): its figures read back by OpenImageIO, and
the device it asks for before its first OpenCL work."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import OpenImageIO as oiio
import pytest

from skinpipe.render.outputs import display_image, write_outputs
from skinpipe.workflow.chain import side_by_side


def test_side_by_side_lays_each_display_png_over_grey_once(tmp_path: Path) -> None:
    """Two renders' display PNGs side by side over an 18% grey backdrop: each pixel is
    its display colour (of the colour, not times coverage) times alpha plus grey times
    one less alpha, within two 8-bit roundings, where the label is not drawn; a
    silhouette pixel is neither doubly darkened nor brightened."""
    rng = np.random.default_rng(2)
    shape = (60, 40)
    colour = rng.random((*shape, 3), np.float32)
    alpha = np.ones((*shape, 1), np.float32)
    alpha[:, :10] = 0.0  # background
    alpha[:, 10:20] = rng.uniform(0.1, 0.9, (shape[0], 10, 1))  # a silhouette
    beauty = np.concatenate([colour * alpha, alpha], axis=2)
    names = []
    for name, scale in (("left", 1.0), ("right", 0.5)):
        write_outputs(tmp_path, name, {"beauty": beauty * np.float32(scale)},
                      "lin_ap1_scene", "ocio://default")
        names.append(tmp_path / f"{name}.png")
    out = side_by_side(*names, tmp_path / "pair.png", ("a", "b"))
    got = oiio.ImageBuf(str(out)).get_pixels(oiio.FLOAT)
    assert got.shape == (shape[0], 2 * shape[1], 3)
    for i, scale in enumerate((1.0, 0.5)):
        a = alpha * np.float32(scale)
        disp, _ = display_image(np.concatenate([colour * a, a], axis=2), "lin_ap1_scene",
                                "ocio://default")
        want = disp * a + 0.18 * (1 - a)
        tile = got[:, i * shape[1]:(i + 1) * shape[1]]
        rows = slice(40, None)  # below the label
        np.testing.assert_allclose(tile[rows], want[rows], atol=2.5 / 255)


def test_the_chain_asks_for_its_device_before_its_first_opencl_work(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The OpenCL loader lists its runtimes once, at the process's first query, and the
    painter's prewarm is the chain's first: `demo --device intel` had found no Intel
    device where a render with `auto` would have left Intel's runtime out."""
    from skinpipe.render.options import RenderOptions
    from skinpipe.workflow import chain

    calls: list[str] = []

    class Stop(Exception):
        pass

    def prewarm(device: object, steps: object) -> None:
        calls.append("prewarm")
        raise Stop

    monkeypatch.setattr(chain, "open_device", lambda spec: calls.append(f"device {spec}"))
    monkeypatch.setattr(chain, "start_prewarm", prewarm)
    with pytest.raises(Stop):
        chain.run_chain(tmp_path / "captures", tmp_path / "mesh.ply", tmp_path / "lm.json",
                        tmp_path / "out", 6, False, True, RenderOptions(device="intel"),
                        "ocio://default")
    assert calls == ["device intel", "prewarm"]
