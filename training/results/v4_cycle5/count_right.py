"""The counts cycle 5's rule reads: per calibration group, the pairs whose chosen pose is right.

    python training/results/v4_cycle5/count_right.py CACHE [MODEL_DIR]

CACHE: a ``benchmarks/calibrate_success.py`` cache whose ``fit`` has computed every pair's
hypotheses (``hypotheses.json``); MODEL_DIR: the model whose stored calibration chooses and
flags (default: the bundled one). Scan pairs are also counted for airplanes and the rest.
Run from the project root.
"""
import sys, json, collections
sys.path.insert(0, 'benchmarks')
import calibrate_success as cs
from pathlib import Path
from logdesc_rt.network import bundled_model_dir, read_manifest
cache = Path(sys.argv[1]); model = Path(sys.argv[2]) if len(sys.argv) > 2 else bundled_model_dir()
cfg = read_manifest(model).runtime_config().verification
rows = json.load(open(cache / 'hypotheses.json'))['rows']
flat = [r for v in rows.values() for r in v]
out = cs.flag_outcomes(flat, cfg)
shapes = cs.pair_shapes(sorted(k for k in out if k.startswith('val_scan/')), 'three-way')
groups = collections.defaultdict(lambda: [0, 0, 0, 0, 0])
for p, o in out.items():
    g = p.split('/')[0]
    keys = [g]
    if g == 'val_scan':
        keys.append('val_scan_' + ('airplane' if shapes[p].startswith('airplane') else 'not_airplane'))
    for k in keys:
        c = groups[k]; c[0] += 1; c[1] += o['unrefined_right']; c[2] += o['refined_right']
        c[3] += o['unrefined_claimed']; c[4] += o['unrefined_claimed'] and o['unrefined_right']
for k in sorted(groups):
    n, u, r, cl, cr = groups[k]
    print(f"{k:26s} pairs {n:4d} unrefined right {u:4d} verified right {r:4d} claimed {cl:4d} right among claimed {cr:4d}")
