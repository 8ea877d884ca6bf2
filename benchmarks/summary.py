"""The results tables of README.md and docs/benchmarks.md, generated from benchmarks/results/.

    python benchmarks/summary.py          # rewrite the tables between their markers
    python benchmarks/summary.py --check  # exit 1 if a table differs from what the files give

Each table sits between ``<!-- NAME:begin -->`` and ``<!-- NAME:end -->``:

- ``results`` (README.md and docs/benchmarks.md): one row per kind of pair, success without /
  with ICP for ``register()`` and Open3D FPFH + RANSAC (KISS-Matcher when a file has it), and
  the median time per pair in the same run.
- ``flag`` (docs/benchmarks.md): the success flag's precision and recall on the same test pairs.
- ``latency`` (docs/benchmarks.md): time per stage at each working size, from the newest
  ``latency*.json``.
- ``large-clouds`` (docs/benchmarks.md): time, error and peak memory per large pair.

A figure a file does not hold is shown as "—". Nothing here measures anything.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
MISSING = "—"

# (label, JSON file under benchmarks/results, key under "summary" or None for the summary itself)
ACCURACY_ROWS = [
    ("ModelNet10 objects, noisy + partial, any relative rotation",
     "modelnet10_any_relative/modelnet10_accuracy.json", "partial_any_relative"),
    ("ModelNet10 objects, noisy + partial, the clouds share no sample",
     "modelnet10_resampled/modelnet10_accuracy.json", "resampled_partial"),
    ("Simulated range scans of unseen shapes", "scan_pairs_test.json", None),
    ("Stanford Bunny, real scan pairs", "bunny.json", "real_pairs"),
    ("Stanford Bunny, the paper's protocol (noisy copies)", "bunny.json", "paper_protocol"),
    ("Bunny mesh (5,000 surface samples) to its real scans", "model_to_scan.json", None),
]
LARGE_CASES = {
    "bunny_40k": "Real Bunny scan pair, 40k x 40k points",
    "merged_120k": "Merged Bunny scans, 120k x 120k points in metres, 1 km from the origin",
    "merged_300k": "Merged Bunny scans, 300k x 300k points in metres, 1 km from the origin",
}
LATENCY_SIZE = "1024"


# ----------------------------------------------------------------------------- reading
def load(name: str) -> dict | None:
    path = RESULTS / name
    if not path.exists():
        return None
    return json.loads(path.read_text())


def number(value) -> float | None:
    """A finite number, or None."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    return None if value != value else float(value)


def percent(value) -> str:
    value = number(value)
    return MISSING if value is None else f"{100 * value:.1f}"


def milliseconds(seconds) -> str:
    seconds = number(seconds)
    return MISSING if seconds is None else f"{1000 * seconds:.0f}"


def pair_of(first: str, second: str) -> str:
    return first if second == MISSING and first == MISSING else f"{first} / {second}"


def method_seconds(entry: dict) -> float | None:
    for key in ("seconds_median", "median_seconds", "seconds"):
        if number(entry.get(key)) is not None:
            return entry[key]
    return None


def kiss_entry(methods: dict) -> dict | None:
    for key, entry in methods.items():
        if "kiss" in key.lower() and isinstance(entry, dict) and not key.endswith("_icp"):
            return entry
    return None


def first_median_ms(entry) -> float | None:
    """The first ``median_ms`` found in a nested dict (the timing files' layout)."""
    if isinstance(entry, dict):
        if number(entry.get("median_ms")) is not None:
            return entry["median_ms"]
        for value in entry.values():
            found = first_median_ms(value)
            if found is not None:
                return found
    return None


def report_of(json_name: str) -> str:
    """The markdown report beside a JSON file (its human-readable twin), else the JSON itself."""
    markdown = Path(json_name).with_suffix(".md")
    return markdown.as_posix() if (RESULTS / markdown).exists() else json_name


def commit_time(commit: str | None) -> int:
    if not commit:
        return 0
    try:
        out = subprocess.run(["git", "show", "-s", "--format=%ct", commit], cwd=ROOT, capture_output=True,
                             text=True, timeout=10)
        return int(out.stdout.strip() or 0)
    except (OSError, ValueError, subprocess.SubprocessError):
        return 0


def newest_latency() -> tuple[str, dict] | None:
    """The latency file measured at the newest commit (its ``machine.commit``), ties by name."""
    found = []
    for path in sorted(RESULTS.glob("latency*.json")):
        data = json.loads(path.read_text())
        found.append((commit_time(data.get("machine", {}).get("commit")), path.name, data))
    if not found:
        return None
    _, name, data = max(found, key=lambda item: (item[0], item[1]))
    return name, data


def pairs_of(data: dict | None, entry: dict) -> int | None:
    """How many pairs a method's figures are over: its own count, the file's, or its rows."""
    data = data or {}
    return (entry.get("pairs") or data.get("pairs")
            or sum(1 for row in data.get("rows", []) if row.get("method") == "logdesc_auto") or None)


# ----------------------------------------------------------------------------- rows
def accuracy_rows() -> list[dict]:
    rows = []
    for label, name, key in ACCURACY_ROWS:
        data = load(name)
        summary = (data or {}).get("summary", {})
        methods = summary.get(key, {}) if key else summary
        if not methods:
            print(f"  {label}: no figures in {name}", file=sys.stderr)
        ours, ours_icp = methods.get("logdesc_auto", {}), methods.get("logdesc_auto_icp", {})
        peer, peer_icp = methods.get("fpfh_ransac", {}), methods.get("fpfh_ransac_icp", {})
        kiss = kiss_entry(methods)
        pairs = pairs_of(data, ours)
        rows.append({
            "label": label, "source": name, "pairs": str(pairs) if pairs else MISSING,
            "ours": pair_of(percent(ours.get("success")), percent(ours_icp.get("success"))),
            "open3d": pair_of(percent(peer.get("success")), percent(peer_icp.get("success"))),
            "kiss": percent(kiss.get("success")) if kiss else MISSING,
            "ours_ms": milliseconds(method_seconds(ours)),
            "open3d_ms": milliseconds(method_seconds(peer)),
            "kiss_ms": milliseconds(method_seconds(kiss)) if kiss else MISSING,
            "has_kiss": kiss is not None,
        })
    return rows


def latency_row(found: tuple[str, dict] | None) -> list[dict]:
    if found is None:
        return []
    name, data = found
    size = data.get("results", {}).get(LATENCY_SIZE, {})
    ours = size.get("onnxruntime", {}).get("stages", {}).get("wall", {})
    peer = size.get("open3d", {}).get("methods", {}).get("fpfh_ransac", {})
    kiss = next((value for key, value in {**size, **size.get("open3d", {}).get("methods", {})}.items()
                 if "kiss" in key.lower()), None)
    ms = lambda value: MISSING if number(value) is None else f"{value:.0f}"  # noqa: E731
    return [{
        "label": f"A Bunny scan and its moved noisy copy, {LATENCY_SIZE} points per cloud (time only)", "source": name,
        "pairs": "1", "ours": MISSING, "open3d": MISSING, "kiss": MISSING,
        "ours_ms": ms(ours.get("median_ms")), "open3d_ms": ms(peer.get("median_ms")),
        "kiss_ms": ms(first_median_ms(kiss)), "has_kiss": kiss is not None,
    }]


def large_cloud_rows(data: dict | None) -> list[dict]:
    if not data:
        return []
    rows = []
    for case, label in LARGE_CASES.items():
        ours = next((r for r in data.get("rows", []) if r.get("case") == case and not r.get("refine")), None)
        peer = next((r for r in data.get("open3d_rows", [])
                     if r.get("case") == case and r.get("method", "").endswith("RANSAC")), None)
        if ours is None and peer is None:
            continue
        rows.append({
            "label": f"{label} (time only)", "source": "large_clouds.json", "pairs": "1",
            "ours": MISSING, "open3d": MISSING, "kiss": MISSING,
            "ours_ms": milliseconds((ours or {}).get("seconds")),
            "open3d_ms": milliseconds((peer or {}).get("seconds")),
            "kiss_ms": MISSING, "has_kiss": False,
        })
    return rows


# ----------------------------------------------------------------------------- tables
def results_table(link_prefix: str | None) -> str:
    """The one results table. ``link_prefix``: relative path from the page to the repository
    root (links to the reports), or None to name the reports, relative to benchmarks/results/,
    as code (the documentation site holds no copy of them)."""
    rows = accuracy_rows() + latency_row(newest_latency()) + large_cloud_rows(load("large_clouds.json"))
    kiss = any(row["has_kiss"] for row in rows)
    header = ["Pairs", "n", "logdesc-rt success %, without / with ICP", "Open3D FPFH + RANSAC success %, "
              "without / with ICP"]
    header += ["KISS-Matcher success %"] if kiss else []
    header += ["logdesc-rt ms / pair", "Open3D ms / pair"] + (["KISS-Matcher ms / pair"] if kiss else [])
    header += ["Made by"]
    lines = ["| " + " | ".join(header) + " |", "| --- | ---: | ---: | ---: |" + " ---: |" * (2 + 2 * kiss) + " --- |"]
    for row in rows:
        report = report_of(row["source"])
        if link_prefix is None:
            source = f"`{report}`"
        else:
            source = f"[{Path(report).name}]({link_prefix}benchmarks/results/{report})"
        cells = [row["label"], row["pairs"], row["ours"], row["open3d"]]
        cells += [row["kiss"]] if kiss else []
        cells += [row["ours_ms"], row["open3d_ms"]] + ([row["kiss_ms"]] if kiss else [])
        cells += [source]
        lines.append("| " + " | ".join(cells) + " |")
        print(f"  {row['label']}  <-  benchmarks/results/{row['source']}")
    return "\n".join(lines)


def flag_table() -> str:
    """The success flag on test data: precision (right among the claimed successes) and recall
    (claimed among the right poses), without / with ICP."""
    lines = ["| Pairs | n | precision %, without / with ICP | recall %, without / with ICP | Made by |",
             "| --- | ---: | ---: | ---: | --- |"]
    for label, name, key in ACCURACY_ROWS:
        data = load(name)
        summary = (data or {}).get("summary", {})
        methods = summary.get(key, {}) if key else summary
        ours, ours_icp = methods.get("logdesc_auto", {}), methods.get("logdesc_auto_icp", {})
        precision = [entry.get("flag_precision", entry.get("right_when_flagged")) for entry in (ours, ours_icp)]
        recall = [entry.get("flag_recall") for entry in (ours, ours_icp)]
        pairs = pairs_of(data, ours) or MISSING
        lines.append(f"| {label} | {pairs} | {pair_of(*map(percent, precision))} | {pair_of(*map(percent, recall))}"
                     f" | `{report_of(name)}` |")
    print("  success flag  <-  the accuracy rows' files")
    return "\n".join(lines)


def peer_name(method: str) -> str:
    if "kiss" in method.lower():
        return "KISS-Matcher"
    return "Open3D " + method.replace("_", " + ").upper()


def latency_table() -> str:
    found = newest_latency()
    if found is None:
        return f"{MISSING} (no benchmarks/results/latency*.json)"
    name, data = found
    results = data.get("results", {})
    sizes = sorted(results, key=lambda size: int(size) if str(size).isdigit() else 0)
    stages: list[str] = []
    for size in sizes:
        for stage in results[size].get("onnxruntime", {}).get("stages", {}):
            if stage not in stages:
                stages.append(stage)
    peers = []
    for size in sizes:
        for method in results[size].get("open3d", {}).get("methods", {}):
            if method not in peers:
                peers.append(method)
    kiss_keys = sorted({key for size in sizes for key in results[size] if "kiss" in key.lower()})
    lines = ["| stage (median ms) | " + " | ".join(f"{size} points" for size in sizes) + " |",
             "| --- |" + " ---: |" * len(sizes)]

    def cell(value) -> str:
        return MISSING if number(value) is None else f"{value:.1f}"

    for stage in stages:
        values = [results[size].get("onnxruntime", {}).get("stages", {}).get(stage, {}).get("median_ms")
                  for size in sizes]
        lines.append(f"| logdesc-rt: {stage} | " + " | ".join(cell(v) for v in values) + " |")
    for method in peers:
        values = [results[size].get("open3d", {}).get("methods", {}).get(method, {}).get("median_ms")
                  for size in sizes]
        lines.append(f"| {peer_name(method)} | "
                     + " | ".join(cell(v) for v in values) + " |")
    for key in kiss_keys:
        values = [first_median_ms(results[size].get(key)) for size in sizes]
        lines.append(f"| KISS-Matcher ({key}) | " + " | ".join(cell(v) for v in values) + " |")
    command = data.get("command", MISSING)
    model = data.get("model", MISSING)
    commit = data.get("machine", {}).get("commit", MISSING)
    cores = data.get("machine", {}).get("cpu_count", MISSING)
    lines += ["", f"From `benchmarks/results/{name}` (model {model}, commit {commit}, {cores} cores): `{command}`."]
    print(f"  latency per stage  <-  benchmarks/results/{name}")
    return "\n".join(lines)


def large_clouds_table() -> str:
    data = load("large_clouds.json")
    if not data:
        return f"{MISSING} (no benchmarks/results/large_clouds.json)"
    lines = ["| pair | method | s | rotation error (deg) | translation error (m) | peak memory (MiB) |",
             "| --- | --- | ---: | ---: | ---: | ---: |"]

    def fmt(value, digits) -> str:
        return MISSING if number(value) is None else f"{value:.{digits}f}"

    for case, label in LARGE_CASES.items():
        entries = [(f"logdesc-rt{' + ' + r['refine'] + ' ICP' if r.get('refine') else ''}", r)
                   for r in data.get("rows", []) if r.get("case") == case]
        entries += [(r.get("method", "Open3D"), r) for r in data.get("open3d_rows", []) if r.get("case") == case]
        for method, r in entries:
            lines.append(f"| {label} | {method} | {fmt(r.get('seconds'), 2)} | {fmt(r.get('rotation_error_deg'), 2)}"
                         f" | {fmt(r.get('translation_error_m'), 4)} | {fmt(r.get('peak_rss_mib'), 0)} |")
    commit = data.get("machine", {}).get("commit", MISSING)
    lines += ["", f"From `benchmarks/results/large_clouds.json` (commit {commit}): `{data.get('command', MISSING)}`."]
    print("  large clouds  <-  benchmarks/results/large_clouds.json")
    return "\n".join(lines)


# ----------------------------------------------------------------------------- pages
def replace_block(text: str, name: str, body: str) -> str:
    begin, end = f"<!-- {name}:begin -->", f"<!-- {name}:end -->"
    if begin not in text or end not in text:
        raise SystemExit(f"summary.py: the markers {begin} ... {end} are missing")
    head, rest = text.split(begin, 1)
    _, tail = rest.split(end, 1)
    return f"{head}{begin}\n{body}\n{end}{tail}"


def rendered() -> dict[Path, str]:
    pages = {}
    readme = ROOT / "README.md"
    print("README.md:")
    pages[readme] = replace_block(readme.read_text(), "results", results_table(link_prefix=""))
    docs = ROOT / "docs" / "benchmarks.md"
    print("docs/benchmarks.md:")
    text = replace_block(docs.read_text(), "results", results_table(link_prefix=None))
    text = replace_block(text, "flag", flag_table())
    text = replace_block(text, "latency", latency_table())
    pages[docs] = replace_block(text, "large-clouds", large_clouds_table())
    return pages


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="exit 1 if a table is stale; write nothing")
    args = parser.parse_args(argv)
    stale = []
    for path, text in rendered().items():
        if path.read_text() != text:
            stale.append(path.relative_to(ROOT).as_posix())
            if not args.check:
                path.write_text(text)
    if args.check and stale:
        print(f"stale: {', '.join(stale)}; run python benchmarks/summary.py", file=sys.stderr)
        return 1
    print(("rewrote: " + ", ".join(stale)) if stale and not args.check else "up to date")
    return 0


if __name__ == "__main__":
    sys.exit(main())
