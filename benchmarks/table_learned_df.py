"""Issue 24, learned Student-t dof: the generators table of loro, the Gaussian model, Student-t df 4 and the learned
dof on the same training draws, from ``bench_hierarchical.py generators`` DRAW records.

Run: ``python benchmarks/table_learned_df.py`` (reads benchmarks/results_issue24/learned_df/*; prints markdown): the
first round's 10 draws; ``--thirty``: the sixth round's 30 draws per generator, every model rerun with the same code
(``generators_*_30.draws``, from ``bench_hierarchical.py generators --draws 30 --sessions 40 --generator uniform t3
heavy gauss`` with ``--likelihood student_t --df learned``, ``--df 4`` and the Gaussian default).
"""

import json
import sys
from pathlib import Path

import numpy as np

D = Path(__file__).resolve().parent / "results_issue24" / "learned_df"
FILES = {"gaussian": "generators_gaussian_draws0-9.draws", "student_t, df 4": "generators_student_t_df4.log",
         "student_t, learned": "generators_student_t_learned.log"}
FILES_30 = {"gaussian": "generators_gaussian_30.draws", "student_t, df 4": "generators_student_t_df4_30.draws",
            "student_t, learned": "generators_student_t_learned_30.draws"}


def records(name):
    return [json.loads(line[5:]) for line in (D / name).read_text().splitlines() if line.startswith("DRAW ")]


def main(argv=()):
    f = lambda v: " / ".join(f"{100 * x:.1f}" for x in v)   # noqa: E731
    recs = {k: records(v) for k, v in (FILES_30 if "--thirty" in argv else FILES).items()}
    gens = list(dict.fromkeys(r["generator"] for r in recs["student_t, learned"]))
    print("| generator | draws | transfer | covered or flagged, mean (%) | 10th percentile over draws (%) | draws under "
          "95 % | width / loro's where loro covers, mean over draws | same, draws where loro >= 95 % | draw-axes "
          "over 1.5x | largest | mass on df <= 6, mean |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for g in gens:
        for i, (k, rs) in enumerate(recs.items()):
            rs = sorted((r for r in rs if r["generator"] == g), key=lambda r: r["draw"])
            if i == 0:
                o = np.array([r["ok_loro"] for r in rs])
                print(f"| {g} | {len(rs)} | loro | {f(o.mean(0))} | {f(np.percentile(o, 10, axis=0))} | "
                      f"{' / '.join(map(str, (o < 0.95).sum(0)))} | 1 | 1 | - | - | - |")
            o = np.array([r["ok_hier"] for r in rs])
            ratio = np.array([r["ratio"] for r in rs])
            ok_l = np.array([r["ok_loro"] for r in rs])
            wl, wh = np.array([r["width_loro"] for r in rs]), np.array([r["width_hier"] for r in rs])
            good = ok_l >= 0.95
            by_draw = " / ".join(f"{wh[good[:, a], a].mean() / wl[good[:, a], a].mean():.2f}" for a in range(3))
            print(f"| {g} | {len(rs)} | {k} | {f(o.mean(0))} | {f(np.percentile(o, 10, axis=0))} | "
                  f"{' / '.join(map(str, (o < 0.95).sum(0)))} | {' / '.join(f'{v:.2f}' for v in ratio.mean(0))} | "
                  f"{by_draw} | {int((ratio > 1.5).sum())} of {ratio.size} | {ratio.max():.2f} | {heavy(rs)} |")


def heavy(rs) -> str:
    """Mean posterior mass on df <= 6 per axis (learned dof only)."""
    if "df_weight" not in rs[0]:
        return "-"
    grid = np.array([np.inf if g is None else g for g in rs[0]["df_grid"]])
    m = np.array([np.asarray(r["df_weight"])[:, grid <= 6].sum(1) for r in rs]).mean(0)
    return " / ".join(f"{v:.2f}" for v in m)


if __name__ == "__main__":
    main(sys.argv[1:])
