"""Counts like count_right.py, with the calibration of a fit report JSON (its verification_config)."""
import sys, json, collections
sys.path.insert(0, 'benchmarks')
import calibrate_success as cs
from logdesc_rt.config import VerificationConfig
cache, report = sys.argv[1], sys.argv[2]
cfg = VerificationConfig.from_dict(json.load(open(report))['verification_config'])
rows = json.load(open(cache + '/hypotheses.json'))['rows']
out = cs.flag_outcomes([r for v in rows.values() for r in v], cfg)
groups = collections.defaultdict(lambda: [0, 0, 0, 0, 0, 0])
for p, o in out.items():
    c = groups[p.split('/')[0]]
    c[0] += 1; c[1] += o['unrefined_right']; c[2] += o['refined_right']
    c[3] += o['unrefined_claimed']; c[4] += o['unrefined_claimed'] and o['unrefined_right']; c[5] += any(h['verified_right'] for h in rows[p])
for k in sorted(groups):
    n, u, r, cl, cr, a = groups[k]
    print(f"{k:24s} pairs {n:4d} unrefined right {u:4d} verified right {r:4d} claimed {cl:4d} right among claimed {cr:4d} any hypothesis right {a:4d}")
