import sys, warnings, time
warnings.simplefilter("ignore")
sys.path.insert(0, sys.argv[1] + "/benchmarks"); sys.path.insert(0, sys.argv[1]); sys.path.insert(0, sys.argv[1] + "/tests")
import bayesmag
assert bayesmag.__file__.startswith(sys.argv[1]), bayesmag.__file__
import bench_hybrid_shift as B
seed, run = int(sys.argv[2]), int(sys.argv[3])
t = time.time()
r = B.leave_one_out_both(B.sessions(8, 600, seed), run, transfer_networks="by_run_folds")
o = r["hierarchical_oof"]
print("OOF", seed, run, "fc", [round(100 * v, 1) for v in o["flagged_or_covered"]], "tau", [round(float(v), 3) for v in o["tau"]],
      "w", [round(float(v), 3) for v in o["width"]], f"{time.time() - t:.0f}s")
