#!/bin/bash
# Issue 24 benchmarks on a 16-core machine: 8 generators x 30 draws x 40 sessions, bench_hybrid_shift seeds 0-2
# (hierarchical and loro), one process each, results tarred into $OUT/res.tgz.
R=/tmp/res; mkdir -p $R
git log -1 --oneline > $R/head.txt 2>&1; nproc >> $R/head.txt
grep -q transfer_uninformed bayesmag/_src/pipeline/settings.py || { echo WRONG_TREE; cat $R/head.txt; exit 3; }
export PYTHONPATH=$PWD JAX_PLATFORMS=cpu MPLBACKEND=Agg PYTHONUNBUFFERED=1 OMP_NUM_THREADS=1
export XLA_FLAGS="--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"
python3 -c "import bayesmag, jax; print(jax.__version__)" >> $R/head.txt 2>&1 || { cat $R/head.txt; exit 4; }
T=${1:-520}
for g in gauss t3 offsets_small cross_only uniform heavy temp_drift correlated; do
  timeout $T python3 benchmarks/bench_hierarchical.py generators --draws 30 --sessions 40 --generator $g > $R/gen_$g.txt 2>&1 &
done
for s in 0 1 2; do
  timeout $T python3 benchmarks/bench_hybrid_shift.py --seeds $s --transfer hierarchical > $R/hyb_h_$s.txt 2>&1 &
  timeout $T python3 benchmarks/bench_hybrid_shift.py --seeds $s > $R/hyb_l_$s.txt 2>&1 &
done
wait
tar czf $OUT/res.tgz -C $R .
tail -n 3 $R/*.txt
