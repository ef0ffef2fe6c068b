import sys, collections, numpy as np
def load(path):
    rows = collections.defaultdict(dict)
    for l in open(path):
        if not l.startswith("| ") or l.startswith("| seed"): continue
        c = [x.strip() for x in l.strip().strip("|").split("|")]
        try: k = (int(c[0]), int(c[1]))
        except ValueError: continue
        num = lambda s: np.array([np.nan if v.strip() == "-" else float(v) for v in s.split("/")])
        rows[k][c[2]] = dict(fc=num(c[5]) / 100, w=num(c[9]), tau=num(c[7]))
    return rows
def summ(rows, seeds):
    ks = [k for k in sorted(rows) if k[0] in seeds]
    base = np.array([rows[k]["loro"]["fc"] for k in ks]) >= 0.95
    wl = np.array([rows[k]["loro"]["w"] for k in ks])
    out = {}
    for t in rows[ks[0]]:
        fc = np.array([rows[k][t]["fc"] for k in ks]); r = np.array([rows[k][t]["w"] for k in ks]) / wl
        miss = [f"{k[0]}-{k[1]} {'xyz'[a]} {100*fc[i,a]:.1f}" for i, k in enumerate(ks) for a in range(3) if fc[i, a] < 0.95]
        over = [int(np.sum(r[base[:, a], a] > 1.5)) for a in range(3)]
        print(f"{t:18s} under95 {'/'.join(str(int(v)) for v in (fc<0.95).sum(0))} ({', '.join(miss)}) | median "
              f"{'/'.join(f'{np.nanmedian(r[base[:,a],a]):.2f}' for a in range(3))} largest "
              f"{'/'.join(f'{np.nanmax(r[base[:,a],a]):.2f}' for a in range(3))} over1.5 {'/'.join(map(str,over))} = {sum(over)} of {int(base.sum())}")
rows = load(sys.argv[1])
for s in sys.argv[2:]:
    a, b = map(int, s.split("-")); print(f"seeds {s}"); summ(rows, set(range(a, b + 1)))
