"""Screenshots of the interactive 3D views, drawn by a real browser (headless Chromium).

Three pages, written by the same calls a user makes (``result.view``, ``AlignmentResult.view``)
and rendered by :func:`logdesc_rt.tools.screenshot.render_page`, the browser test's renderer:

    good_pair     the demo pair (``logdesc-rt demo``), with its ground truth in the title
    failed_pair   the first pair of neighbouring real Bunny scans (file order, 45 deg apart)
                  that ``register()`` does not flag a success, at 1024 points per scan
    align_bunny   ``align()`` of the ten real Bunny scans (FPS to 4096 points each, ICP)

Illustrations only: the Bunny pair is not chosen for a figure of merit, and nothing is tuned.

    python benchmarks/view_screenshots.py [--out benchmarks/results/views] [--pages DIR]

Writes ``<out>/{good_pair,failed_pair,align_bunny}.png`` and the pages to ``--pages``
(default: a temporary folder; each page embeds plotly.js, ~5 MB, so they are not committed).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np  # noqa: E402
from common import DATA_ROOT, RESULTS, command_line  # noqa: E402

import logdesc_rt  # noqa: E402
from logdesc_rt.align import AlignConfig  # noqa: E402
from logdesc_rt.demo import make_demo_pair  # noqa: E402
from logdesc_rt.io import read_point_cloud, read_stanford_conf  # noqa: E402
from logdesc_rt.sampling import farthest_point_sampling  # noqa: E402
from logdesc_rt.tools.screenshot import render_page  # noqa: E402

NEIGHBOURS = ("bun000.ply", "bun045.ply", "bun090.ply", "bun180.ply", "bun270.ply", "bun315.ply")


def _fps(points: np.ndarray, count: int) -> np.ndarray:
    return points[farthest_point_sampling(points, min(count, len(points)))]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=RESULTS / "views")
    parser.add_argument("--pages", type=Path, default=None)
    parser.add_argument("--data-root", type=Path, default=DATA_ROOT)
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    pages = args.pages or Path(tempfile.mkdtemp(prefix="logdesc_views_"))
    pages.mkdir(parents=True, exist_ok=True)
    notes = []

    pair = make_demo_pair()
    result = logdesc_rt.register(pair.source, pair.target)
    page = result.view(pages / "good_pair.html", pair.source, pair.target, true_transformation=pair.true_transformation)
    notes.append(("good_pair", page, f"demo pair: success {result.success}, confidence {result.confidence:.2f}"))

    folder = args.data_root / "stanford_bunny" / "data"
    poses = read_stanford_conf(folder / "bun.conf")
    failed = None
    for first, second in zip(NEIGHBOURS, NEIGHBOURS[1:]):
        source = _fps(read_point_cloud(folder / first), 1024)
        target = _fps(read_point_cloud(folder / second), 1024)
        result = logdesc_rt.register(source, target)
        if not result.success:
            truth = np.linalg.inv(poses[second]) @ poses[first]
            page = result.view(pages / "failed_pair.html", source, target, true_transformation=truth)
            failed = (first, second)
            notes.append(("failed_pair", page, f"{first} -> {second}: success {result.success}, "
                                               f"confidence {result.confidence:.2f}"))
            break
    if failed is None:
        print("every neighbouring Bunny pair registered: no failed pair to show", file=sys.stderr)

    names = sorted(poses)
    scans = [_fps(read_point_cloud(folder / name), 4096) for name in names]
    alignment = logdesc_rt.align(scans, names=names, config=AlignConfig(), workers=0, progress=False)
    page = alignment.view(pages / "align_bunny.html", scans)
    notes.append(("align_bunny", page, f"{len(alignment.poses)} of {len(names)} scans placed"))

    for stem, page, note in notes:
        render = render_page(page, args.out / f"{stem}.png", width=1200, height=800)
        if render.errors:
            raise SystemExit(f"{page}: the browser logged errors: {render.errors}")
        print(f"{stem}: {note}; {render.screenshot} in {render.seconds:.1f} s")
    (args.out / "README.md").write_text(
        "# Screenshots of the 3D views\n\n"
        "Drawn by headless Chromium (WebGL on SwiftShader) from the pages `result.view()` and "
        "`AlignmentResult.view()` write.\n\n"
        + "".join(f"- `{stem}.png`: {note}\n" for stem, _, note in notes)
        + f"\nCommand: `{command_line()}`\n"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
