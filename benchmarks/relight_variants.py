"""Issue 38 follow-up: the old ``gp`` grid, the current (wider) one, and stacked smoothers, 8 folds.

    PYTHONPATH=. python benchmarks/relight_variants.py ../shared/data/realrti-3/item9 --out /tmp/i9.json

("wide" is the grid of the ``ps_lab`` imported: run it against this checkout.)

Per fold (lights ``i % 8 == f`` held out): each variant's choice by leave-one-light-out on 2048
pixels of the training lights, then the held-out grey sRGB PSNR (the judged metric) of its full
smoother weights on 40 000 random pixels. Prints one line per fold (docs/results.md, "Eight folds against RelightLab").
"""
import argparse, itertools, json, time

import numpy as np
from pathlib import Path
from PIL import Image
from ps_lab.appearance import choice as ac
from ps_lab.io.encoding import srgb_to_linear

parser = argparse.ArgumentParser()
parser.add_argument('capture', type=Path)
parser.add_argument('--out', type=Path, default=None)
args = parser.parse_args()
src = args.capture
item = src.name
rows = [l.split() for l in (src/'dirs.lp').read_text().splitlines()[1:] if len(l.split()) >= 4]
L = np.array([[float(v) for v in r[1:4]] for r in rows]); L /= np.linalg.norm(L, axis=1, keepdims=True)
imgs = np.stack([np.asarray(Image.open(src/r[0]).convert('RGB')) for r in rows]).astype(np.float64)/255
n, H, W, _ = imgs.shape
rng = np.random.default_rng(0)
perm = rng.permutation(H*W)
evalpix = perm[:min(H*W, 40000)]
samp = np.sort(perm[-2048*4:])[::4]   # 2048 pixels for the choice
lin = srgb_to_linear(imgs.reshape(n, H*W, 3)).astype(np.float64)
E = lin[:, evalpix]; S = lin[:, samp]
ev_truth = ac.grey_srgb(np.clip(E, 0, 1))
Y = {sp: ac.encode(E, sp) for sp in ('linear', 'srgb')}

GRIDS = {k: ac.candidates(k) for k in ac.AUTO_MODELS}  # the old grid: gp as before issue 38's follow-up
GRIDS['gp'] = [{'sigma': float(s), 'ridge': r} for s in np.geomspace(0.15, 1.2, 5) for r in (1e-3, 1e-2, 1e-1)]
WIDE = {k: ac.candidates(k) for k in ac.AUTO_MODELS}
# also tried (never chosen on realrti-3), WIDE['bln'] =
# [{'sigma': float(s), 'resolution': r} for s in np.geomspace(0.05, 0.5, 7) for r in (8, 16, 32)]

def loo_score(Wl, y, truth, space):
    n_, m, c = y.shape
    p = ac._decode((Wl @ y.reshape(n_, -1)).reshape(n_, m, c), space)
    return float(np.mean(ac.psnr_per_light(ac.grey_srgb(p), truth)))

def heldout(Wh, space):  # Wh (h, ntrain) held-out weights
    y = Y[space][tr]
    p = ac._decode(np.einsum('hn,nmc->hmc', Wh, y), space)
    return float(np.mean(ac.psnr_per_light(ac.grey_srgb(p), ev_truth[ho])))

out = {}
for f in range(8):
    t0 = time.time()
    tr = np.array([i for i in range(n) if i % 8 != f]); ho = np.array([i for i in range(n) if i % 8 == f])
    Lt, Lh = L[tr], L[ho]
    s = S[tr]; truth = ac.grey_srgb(np.clip(s, 0, 1))
    cand = []  # (score, model, space, params, LOOmatrix)
    for grids, tag in ((GRIDS, 'base'), (WIDE, 'wide')):
        for space in ('linear', 'srgb'):
            y = ac.encode(s, space)
            for model in ac.AUTO_MODELS:
                for p in grids[model]:
                    if tag == 'wide' and p in GRIDS[model]:
                        continue
                    Wl = ac.loo_weights(model, p, Lt)
                    if Wl is None:  # not a candidate on these lights
                        continue
                    cand.append(dict(score=loo_score(Wl, y, truth, space), model=model, space=space,
                                     params=p, W=Wl, tag=tag))
    base = [c for c in cand if c['tag'] == 'base']
    res = {}
    def ho_of(c):
        return ac.predict_weights(c['model'], c['params'], Lt, Lh)
    cur = max(base, key=lambda c: c['score'])
    res['current'] = (heldout(ho_of(cur), cur['space']), f"{cur['model']}/{cur['space']} {cur['params']}")
    wb = max(cand, key=lambda c: c['score'])
    res['wide'] = (heldout(ho_of(wb), wb['space']), f"{wb['model']}/{wb['space']} {wb['params']}")
    # stacking: best per model in each space, top-k models, alpha simplex grid on LOO
    for tagset, nm in ((('base',), 'stack'), (('base', 'wide'), 'stackwide')):
        pool = [c for c in cand if c['tag'] in tagset]
        best_stack = None
        for space in ('linear', 'srgb'):
            y = ac.encode(s, space)
            per = {}
            for c in pool:
                if c['space'] == space and (c['model'] not in per or c['score'] > per[c['model']]['score']):
                    per[c['model']] = c
            top = sorted(per.values(), key=lambda c: -c['score'])
            for k in (2, 3):
                cs = top[:k]
                for a in itertools.product(np.arange(0, 1.01, 0.1), repeat=k - 1):
                    if sum(a) > 1 + 1e-9: continue
                    al = list(a) + [1 - sum(a)]
                    Wl = sum(ai * c['W'] for ai, c in zip(al, cs))
                    sc = loo_score(Wl, y, truth, space)
                    if best_stack is None or sc > best_stack[0] + 1e-9:
                        best_stack = (sc, space, cs, al, k)
        sc, space, cs, al, k = best_stack
        Wh = sum(ai * ho_of(c) for ai, c in zip(al, cs))
        res[nm] = (heldout(Wh, space), f"{space} " + " + ".join(f"{ai:.1f}*{c['model']}" for ai, c in zip(al, cs)))
        # 2-only variant
    out[f] = res
    print(item, f, {k: (round(v[0], 2), v[1]) for k, v in res.items()}, f"{time.time()-t0:.0f}s", flush=True)
if args.out is not None:
    args.out.write_text(json.dumps(out, indent=1))
