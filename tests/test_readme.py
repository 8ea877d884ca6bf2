"""The README's quickstart runs verbatim."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

README = Path(__file__).resolve().parents[1] / "README.md"


def test_quickstart_snippet_runs(capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # the snippet writes its 3D page into the working folder
    text = README.read_text()
    section = text[text.index("## Quickstart (Python)"):]
    snippet = re.search(r"```python\n(.*?)```", section, re.DOTALL).group(1)
    namespace: dict = {}
    exec(compile(snippet, "README quickstart", "exec"), namespace)
    printed = capsys.readouterr().out
    result, pair = namespace["result"], namespace["pair"]
    # What it prints is the registration it ran: the matrix (numpy's print) and the timings.
    assert str(result.transformation) in printed
    assert str(result.timings) in printed
    # And the registration is right: the demo pair has a known answer.
    from logdesc_rt.metrics import rotation_error_deg

    truth = pair.true_transformation
    assert float(rotation_error_deg(result.rotation, truth[:3, :3])) < 2.0
    assert np.linalg.norm(result.translation - truth[:3, 3]) < 0.05 * np.linalg.norm(np.ptp(pair.source, axis=0))
    assert (tmp_path / "pair.html").stat().st_size > 1_000_000  # the page, plotly.js inside
