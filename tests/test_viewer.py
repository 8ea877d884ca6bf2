"""The interactive 3D view: a self-contained page with the clouds, residual colours, matches
and verdict, from the Python API and the CLI; and a real browser that draws it (headless
Chromium with WebGL on the CPU), screenshots it and finds it neither blank nor erroring."""

from __future__ import annotations

import os
import re

import numpy as np
import pytest

pytest.importorskip("plotly")

import logdesc_rt
from logdesc_rt.demo import make_demo_pair
from logdesc_rt.tools.cli import main
from logdesc_rt.tools.screenshot import browser_available, render_page

# Set by .ci/run, which installs Chromium: the browser test must run there, not skip.
REQUIRE_BROWSER = "LOGDESC_REQUIRE_BROWSER"


@pytest.fixture(scope="module")
def demo_result():
    pair = make_demo_pair()
    return pair, logdesc_rt.register(pair.source, pair.target)


def _trace_names(page: str) -> list[str]:
    return re.findall(r'"name":"([^"]*)"', page)


def test_the_page_is_self_contained_and_shows_every_layer(tmp_path, demo_result):
    pair, result = demo_result
    path = result.view(tmp_path / "view.html", pair.source, pair.target, true_transformation=pair.true_transformation)
    page = path.read_text()
    # Offline: plotly.js is inside, and no script or stylesheet is fetched from anywhere.
    assert not re.search(r'<script[^>]+src=["\']https?:', page)
    assert not re.search(r'<link[^>]+href=["\']https?:', page)
    assert "plotly.js" in page.lower() or "Plotly" in page
    names = _trace_names(page)
    for layer in ("target", "source as given", "source moved, colour = distance to target",
                  "source moved, shifted beside the target", "matches that agree with the pose"):
        assert any(name.startswith(layer) for name in names), (layer, names)
    assert "SUCCESS (confidence" in page and "rotation error" in page


def test_large_clouds_are_thinned_and_the_page_says_so(tmp_path):
    rng = np.random.default_rng(0)
    source = rng.normal(size=(3000, 3))
    moved = source + [0.1, 0.0, 0.0]
    from logdesc_rt.tools.viewer import write_registration_view

    transformation = np.eye(4)
    transformation[0, 3] = 0.1
    page = write_registration_view(tmp_path / "v.html", source, moved, transformation=transformation,
                                   max_points=1000).read_text()
    assert "target (1,000 of 3,000 points shown)" in page
    small = write_registration_view(tmp_path / "w.html", source, moved, transformation=transformation).read_text()
    assert "target (3,000 points)" in small


def test_a_failed_pair_says_so_in_its_title(tmp_path):
    rng = np.random.default_rng(1)
    source, target = rng.normal(size=(400, 3)), rng.uniform(-1, 1, size=(400, 3))  # nothing to register
    result = logdesc_rt.register(source, target)
    assert not result.success
    page = result.view(tmp_path / "failed.html", source, target).read_text()
    assert "NOT A SUCCESS" in page


def test_cli_writes_views_for_register_demo_and_align(tmp_path, sphere):
    pair = make_demo_pair()
    source, target = tmp_path / "s.ply", tmp_path / "t.ply"
    logdesc_rt.write_point_cloud(source, pair.source)
    logdesc_rt.write_point_cloud(target, pair.target)
    assert main(["register", str(source), str(target), "--view", str(tmp_path / "r.html"), "--quiet"]) == 0
    assert main(["demo", "--view", str(tmp_path / "d.html"), "--quiet"]) == 0
    third = tmp_path / "u.ply"
    logdesc_rt.write_point_cloud(third, pair.source @ np.diag([1.0, -1.0, -1.0]))  # source turned half a turn
    code = main(["align", str(source), str(target), str(third), "--out", str(tmp_path / "poses.json"),
                 "--view", str(tmp_path / "a.html"), "--workers", "0", "--quiet", "--allow-failure"])
    assert code == 0
    for name in ("r.html", "d.html", "a.html"):
        assert (tmp_path / name).stat().st_size > 1_000_000  # plotly.js embedded
    assert "scans aligned, coloured by scan" in (tmp_path / "a.html").read_text()


def test_cli_checks_the_view_path_before_any_work(tmp_path, capsys):
    code = main(["demo", "--view", str(tmp_path / "view.png")])
    assert code == 2 and "--view" in capsys.readouterr().err
    code = main(["demo", "--view", str(tmp_path / "missing" / "view.html")])
    assert code == 2


def _require_browser() -> None:
    missing = browser_available()
    if missing:
        if os.environ.get(REQUIRE_BROWSER):
            pytest.fail(f"{REQUIRE_BROWSER} is set but {missing}")
        pytest.skip(missing)


def _not_blank(path) -> tuple[float, int]:
    """(share of pixels that are not the white background, distinct colours) of a PNG."""
    from PIL import Image

    image = np.asarray(Image.open(path).convert("RGB"))
    drawn = np.any(image < 235, axis=2).mean()
    colours = len(np.unique(image.reshape(-1, 3), axis=0))
    return float(drawn), colours


def test_a_real_browser_draws_the_page_without_errors(tmp_path, demo_result):
    _require_browser()
    pair, result = demo_result
    page = result.view(tmp_path / "view.html", pair.source, pair.target)
    render = render_page(page, tmp_path / "view.png")
    assert render.webgl_canvases >= 1
    assert render.errors == [], render.messages
    drawn, colours = _not_blank(render.screenshot)
    assert drawn > 0.02 and colours > 50, (drawn, colours)
    # A page with nothing in it is blank by this measure: the check can fail.
    empty = tmp_path / "empty.html"
    empty.write_text("<html><body><canvas id='c' width='10' height='10'></canvas><script>"
                     "document.getElementById('c').getContext('webgl')</script></body></html>")
    blank_drawn, _ = _not_blank(render_page(empty, tmp_path / "empty.png", settle_s=0.2).screenshot)
    assert blank_drawn < 0.02
